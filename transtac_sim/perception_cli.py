"""The perception commands of ``transtac-sim`` (detect, train-detector, track, calibrate, reconstruct). Each calls one library
function of ``transtac_sim.perception`` and prints its report; bad input ends with one red line."""

from __future__ import annotations

import shlex
import sys
from pathlib import Path

import typer
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

console = Console()


def _fail(e: Exception) -> None:
    console.print(f"[bold red]error:[/] {e}", soft_wrap=True)
    raise typer.Exit(2) from None


def register(app: typer.Typer) -> None:
    @app.command()
    def detect(images: Path = typer.Argument(..., help="an image, a folder of images, or a dataset folder"),
               out: Path = typer.Option(..., help="detection file to write (JSON)"),
               method: str = typer.Option("learned", help="learned (the network) or blob (the classical baseline)"),
               model: Path = typer.Option(None, help="detector model (.pt); default: the shipped one"),
               device: str = typer.Option("auto", help="auto, cpu or cuda"),
               refine: bool = typer.Option(True, help="refine centres by their intensity centroid"),
               preview: Path = typer.Option(None, help="also write a PNG of the first image with its markers circled"),
               ) -> None:
        """Detect markers in UV images and write the pipeline's detection file."""
        from transtac_sim.perception.detect import detect_images
        from transtac_sim.perception.errors import PerceptionInputError

        try:
            with Progress(TextColumn("detecting"), BarColumn(), TextColumn("{task.completed}/{task.total} images"),
                          TimeRemainingColumn(), console=console, transient=True) as bar:
                task = bar.add_task("detect", total=None)
                rep = detect_images(images, out, method, model, device, refine, preview,
                                    progress=lambda done, total: bar.update(task, completed=done, total=total))
        except (PerceptionInputError, ValueError) as e:
            _fail(e)
        per = ", ".join(f"{k} {1000 * v / rep.images:.1f} ms" for k, v in rep.seconds.items())
        console.print(f"[bold]{rep.images}[/] image(s), {rep.markers} markers ({rep.markers / rep.images:.1f} per image) "
                      f"by {rep.method}{f' ({rep.model})' if rep.model else ''}; per image: {per}")
        console.print(f"  wrote {rep.out}" + (f" and {rep.preview}" if rep.preview else ""))

    @app.command("train-detector")
    def train_detector_cmd(datasets: list[Path] = typer.Argument(..., help="dataset folders (transtac-sim generate)"),
                           out: Path = typer.Option(..., help="model file to write (.pt; the .onnx beside it)"),
                           steps: int = typer.Option(3000, min=1), batch: int = typer.Option(16, min=1),
                           crop: int = typer.Option(128, min=32, help="training crop size, px (multiple of 8)"),
                           width: int = typer.Option(16, min=4, help="network width (channels at stride 2)"),
                           correlation_weight: float = typer.Option(0.0, min=0.0, help="lambda of the correlation term"),
                           context: bool = typer.Option(False, help="add MarkerNet's stride-16 context level"),
                           learning_rate: float = typer.Option(3e-3, min=0.0),
                           device: str = typer.Option("auto", help="auto, cpu or cuda"),
                           eval_every: int = typer.Option(500, min=1), seed: int = typer.Option(0)) -> None:
        """Train the learned marker detector on generated datasets (split by sequence)."""
        from transtac_sim.perception.errors import PerceptionInputError
        from transtac_sim.perception.training.train import TrainConfig, train_detector

        cfg = TrainConfig(steps=steps, batch=batch, crop_px=crop, width=width, context=context,
                          correlation_weight=correlation_weight,
                          learning_rate=learning_rate, device=device, eval_every=eval_every, seed=seed)
        command = "transtac-sim " + " ".join(shlex.quote(a) for a in sys.argv[1:])
        recall = ["-"]
        try:
            with Progress(TextColumn("training"), BarColumn(), TextColumn("{task.completed}/{task.total} steps"),
                          TextColumn("loss {task.fields[loss]:.4f}  val recall@2px {task.fields[recall]}"),
                          TimeRemainingColumn(), console=console) as bar:
                task = bar.add_task("train", total=steps, loss=float("nan"), recall="-")

                def progress(step: int, loss: float, val: dict | None) -> None:
                    if val:
                        recall[0] = f"{val['recall@2px']:.4f} (precision {val['precision@2px']:.4f})"
                    bar.update(task, completed=step, loss=loss, recall=recall[0])

                rep = train_detector(datasets, out, cfg, progress, command)
        except (PerceptionInputError, ValueError) as e:
            _fail(e)
        console.print(f"trained on {rep.train_images} images ({rep.val_images} validation) in {rep.seconds:.0f} s on {rep.device}")
        if rep.val:
            v = rep.val[-1]
            console.print(f"  validation: precision {v['precision@2px']:.4f}, recall {v['recall@2px']:.4f} at 2 px, "
                          f"median error {v['error_median_px']:.3f} px (raw offset head)")
        console.print(f"  wrote {rep.model} and {rep.model.with_suffix('.onnx')}")

    @app.command()
    def track(images: Path = typer.Argument(..., help="a folder of frames (name order) or a dataset folder"),
              out: Path = typer.Option(..., help="tracking file to write (JSON)"),
              method: str = typer.Option("bytetrack", help="bytetrack or flow (the optical-flow baseline)"),
              detector: str = typer.Option("learned", help="learned or blob"),
              model: Path = typer.Option(None, help="detector model (.pt); default: the shipped one"),
              sequence: str = typer.Option(None, help="dataset sequence (default: the first)"),
              camera: str = typer.Option("left", help="dataset camera: left or right"),
              device: str = typer.Option("auto", help="auto, cpu or cuda")) -> None:
        """Track markers over a sequence of UV images: per-frame track ids and displacements."""
        from transtac_sim.perception.errors import PerceptionInputError
        from transtac_sim.perception.track import track_images

        try:
            with Progress(TextColumn("detecting"), BarColumn(), TextColumn("{task.completed}/{task.total} frames"),
                          TimeRemainingColumn(), console=console, transient=True) as bar:
                task = bar.add_task("track", total=None)
                rep = track_images(images, out, method, detector, model, sequence, camera, device,
                                   progress=lambda done, total: bar.update(task, completed=done, total=total))
        except (PerceptionInputError, ValueError) as e:
            _fail(e)
        console.print(f"[bold]{rep.frames}[/] frame(s), {rep.tracks} tracks by {method} "
                      f"(detect {rep.seconds['detect']:.2f} s, track {rep.seconds['track']:.2f} s)")
        console.print(f"  wrote {rep.out}")

    @app.command()
    def reconstruct(out: Path = typer.Option(..., help="output folder (frames/, summary.json, preview.png)"),
                    dataset: Path = typer.Option(None, help="a generated dataset (its calibration.json and UV images)"),
                    sequence: str = typer.Option(None, help="dataset sequence (default: the first)"),
                    calibration: Path = typer.Option(None, help="calibration.json (with --left and --right)"),
                    left: Path = typer.Option(None, help="left camera: an image, a folder of images or a video"),
                    right: Path = typer.Option(None, help="right camera: as --left, paired in sorted order"),
                    matcher: str = typer.Option("delaunay", help="delaunay, hungarian, epipolar_nn, farneback or sgbm"),
                    detector: str = typer.Option("learned", help="learned or blob"),
                    model: Path = typer.Option(None, help="detector model (.pt); default: the shipped one"),
                    stack: Path = typer.Option(None, help="flat-stack JSON for refraction-aware triangulation "
                                                          "(stereo/triangulation.py); without it: linear"),
                    dense: str = typer.Option("none", help="none, sgbm, or onnx (a local learned stereo model: "
                                                           "--stereo-model): dense depth of the white-light pair"),
                    stereo_model: Path = typer.Option(None, help="ONNX stereo model file for --dense onnx "
                                                                 "(docs/formats.md; never downloaded)"),
                    anchors: str = typer.Option("markers", help="markers, or distance-aware (markers plus object "
                                                                "features; needs --stack with gel_thickness_mm)"),
                    preview: str = typer.Option("png", help="png (last frame), video (preview.mp4, every frame) or none"),
                    left_white: Path = typer.Option(None, help="left white-light images (with --dense, without --dataset)"),
                    right_white: Path = typer.Option(None, help="right white-light images (with --dense, without --dataset)"),
                    device: str = typer.Option("auto", help="auto, cpu or cuda")) -> None:
        """3D marker positions from both cameras: detect, track, match and triangulate every frame."""
        from transtac_sim.perception.errors import PerceptionInputError
        from transtac_sim.perception.reconstruct import reconstruct as run

        try:
            with Progress(TextColumn("reconstructing"), BarColumn(), TextColumn("{task.completed}/{task.total} frames"),
                          TimeRemainingColumn(), console=console, transient=True) as bar:
                task = bar.add_task("reconstruct", total=None)
                rep = run(out, dataset=dataset, sequence=sequence, calibration=calibration, left=left, right=right,
                          matcher=matcher, detector=detector, model=model, stack=stack, device=device,
                          dense=dense, stereo_model=stereo_model, anchors=anchors, left_white=left_white,
                          right_white=right_white, preview=preview,
                          progress=lambda done, total: bar.update(task, completed=done, total=total))
        except (PerceptionInputError, ValueError) as e:
            _fail(e)
        console.print(f"[bold]{rep.frames}[/] frame(s), {rep.mean_matches:.1f} matches per frame ({matcher}, "
                      f"{rep.triangulation} triangulation); per frame: detect {1000 * rep.seconds['detect']:.0f} ms, "
                      f"track {1000 * rep.seconds['track']:.0f} ms")
        shown = {"png": ", preview.png", "video": ", preview.mp4", "none": ""}[preview]
        console.print(f"  wrote {rep.out}/frames/, summary.json{shown}" + (", dense/" if dense != "none" else ""))

    @app.command()
    def calibrate(left: Path = typer.Option(..., help="left camera's chessboard images (a folder, sorted)"),
                  right: Path = typer.Option(..., help="right camera's images of the same board views"),
                  out: Path = typer.Option(..., help="calibration.json to write"),
                  board: str = typer.Option(..., help="inner corners, columns x rows, e.g. 9x6"),
                  square_mm: float = typer.Option(..., min=0.0, help="chessboard square size, mm")) -> None:
        """Stereo calibration from chessboard images of both cameras (OpenCV), as calibration.json."""
        from transtac_sim.perception.errors import PerceptionInputError
        from transtac_sim.perception.stereo.board_calibration import calibrate_stereo

        try:
            cols, rows = (int(x) for x in board.lower().split("x"))
        except ValueError:
            _fail(ValueError(f"--board {board!r}: give inner corners as COLUMNSxROWS, e.g. 9x6"))
        if cols < 2 or rows < 2:
            _fail(ValueError(f"--board {board!r}: at least 2x2 inner corners"))
        if not square_mm > 0.0:  # NaN too
            _fail(ValueError(f"--square-mm {square_mm}: the squares' size, > 0 mm"))
        try:
            with console.status("finding the board and calibrating..."):
                rep = calibrate_stereo(left, right, out, (cols, rows), square_mm)
        except PerceptionInputError as e:
            _fail(e)
        console.print(f"{rep.pairs_used} of {rep.pairs_total} pairs used; RMS reprojection left {rep.rms_left_px:.3f} px, "
                      f"right {rep.rms_right_px:.3f} px, stereo {rep.rms_stereo_px:.3f} px; baseline {rep.baseline_mm:.3f} mm, "
                      f"f = {rep.focal_px[0]:.2f} / {rep.focal_px[1]:.2f} px")
        console.print(f"  wrote {rep.out}")
