"""Two trees' timings of the same FEM profile, alternated, and the change's ratio with a bootstrap interval.

    python scripts/paired_timings.py run BEFORE_ROOT OUT --pairs 8 -- scenes/press_slide.toml --device cuda \
        --frames 10 --skip-first --passes 2
    python scripts/paired_timings.py summarize OUT

On a shared machine one run of a frame loop moves by up to about 10 % from the next (BENCHMARKS.md
``fem_launches_folded_gpu``), more than many changes move it, and the speed of a machine drifts within a lease. So a
change is measured as pairs: ``run`` starts ``scripts/fem_phase_profile.py`` with the tree before (``BEFORE_ROOT``: an
exported tree holding ``transtac_sim`` and ``scripts``, put first on ``PYTHONPATH``; its own script runs) and with this
tree (this checkout first on ``PYTHONPATH``), ``--pairs`` times, the order swapped in every other pair (so that a
machine that drifts within a pair favours neither), and writes each run's output to ``OUT/b<k>.txt`` and
``OUT/a<k>.txt``. Both runs start in this checkout, so the scene, material and hardware files named by relative paths
are this tree's. ``summarize`` reads those files (the profile's summary line, "... N frame(s), S s, I Newton iterations
..."): each tree's median seconds and Newton iterations, and the after/before ratio of each pair with their median and
a 95 % percentile bootstrap interval of that median (resampling the pairs, a fixed seed). An interval that holds 1 says
the runs cannot tell the trees apart. With few pairs (under about 10) the interval's ends fall on pair ratios and it is
likely narrower than the true uncertainty: read it as a lower bound on how little is known.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import typer

REPO = Path(__file__).resolve().parents[1]
SUMMARY = re.compile(r"(\d+) frame\(s\), ([0-9.]+) s, (\d+) Newton iterations")
BOOTSTRAP_SAMPLES = 10_000

app = typer.Typer(add_completion=False, help=__doc__.split("\n")[0])


@dataclass(frozen=True)
class PairedSummary:
    """A paired comparison of seconds (``summarize``)."""

    before_s: list[float]
    after_s: list[float]
    before_iterations: list[int]
    after_iterations: list[int]
    ratio_median: float  # after / before, pair by pair
    ratio_interval: tuple[float, float]  # 95 % percentile bootstrap interval of that median

    def lines(self) -> list[str]:
        def span(values) -> str:
            return f"median {np.median(values):.3f} ({min(values):.3f}-{max(values):.3f})"

        low, high = self.ratio_interval
        return [f"pairs: {len(self.before_s)}",
                f"before: s {span(self.before_s)}, Newton iterations {min(self.before_iterations)}-"
                f"{max(self.before_iterations)}",
                f"after: s {span(self.after_s)}, Newton iterations {min(self.after_iterations)}-"
                f"{max(self.after_iterations)}",
                f"after / before, pair by pair: median {self.ratio_median:.3f}, 95 % bootstrap interval "
                f"{low:.3f}-{high:.3f}" + (" (holds 1: no difference resolved)" if low <= 1.0 <= high else "")]


def profile_summary(text: str) -> tuple[float, int]:
    """(seconds, Newton iterations) of the counted frames in ``fem_phase_profile.py``'s output (its last summary line);
    ValueError where there is none (the run failed)."""
    found = SUMMARY.findall(text)
    if not found:
        raise ValueError("no 'N frame(s), S s, I Newton iterations' summary line: did the profile run fail?")
    _, seconds, iterations = found[-1]
    return float(seconds), int(iterations)


def median_interval(values: np.ndarray, samples: int = BOOTSTRAP_SAMPLES, seed: int = 0) -> tuple[float, float]:
    """95 % percentile bootstrap interval of the median of ``values`` (resampled with replacement)."""
    rng = np.random.default_rng(seed)
    medians = np.median(rng.choice(values, size=(samples, len(values)), replace=True), axis=1)
    low, high = np.percentile(medians, [2.5, 97.5])
    return float(low), float(high)


def summarize_pairs(before: list[tuple[float, int]], after: list[tuple[float, int]]) -> PairedSummary:
    """The paired comparison of (seconds, Newton iterations) runs, in the order they were made."""
    if not before or len(before) != len(after):
        raise ValueError(f"need as many runs after as before, at least one each; got {len(before)} and {len(after)}")
    ratios = np.array([a[0] / b[0] for b, a in zip(before, after, strict=True)])
    return PairedSummary([b[0] for b in before], [a[0] for a in after], [b[1] for b in before],
                         [a[1] for a in after], float(np.median(ratios)), median_interval(ratios))


def read_pairs(out: Path) -> PairedSummary:
    """``summarize_pairs`` of the ``b<k>.txt`` and ``a<k>.txt`` files in ``out`` (k = 1, 2, ... as long as both are
    there)."""
    before, after, k = [], [], 1
    while (out / f"b{k}.txt").exists() and (out / f"a{k}.txt").exists():
        for tree, runs in (("b", before), ("a", after)):
            path = out / f"{tree}{k}.txt"
            try:
                runs.append(profile_summary(path.read_text()))
            except ValueError as error:
                raise ValueError(f"{path}: {error}") from None
        k += 1
    if not before:
        raise ValueError(f"{out}: no b1.txt and a1.txt")
    return summarize_pairs(before, after)


@app.command()
def run(before_root: Path = typer.Argument(..., help="an exported tree (transtac_sim/, scripts/) of the code before"),
        out: Path = typer.Argument(..., help="folder for the runs' outputs (b<k>.txt, a<k>.txt)"),
        pairs: int = typer.Option(8, min=1, help="runs of each tree, alternated"),
        profile_args: list[str] = typer.Argument(None, help="after --: fem_phase_profile.py's arguments")) -> None:
    """Alternated runs of scripts/fem_phase_profile.py with the tree before and this tree, then ``summarize``."""
    before_root = before_root.resolve()
    script = before_root / "scripts" / "fem_phase_profile.py"
    if not (before_root / "transtac_sim").is_dir() or not script.is_file():
        raise typer.BadParameter(f"{before_root} has no transtac_sim/ and scripts/fem_phase_profile.py: export one "
                                 "with git archive REV transtac_sim hardware_models materials scenes scripts")
    out.mkdir(parents=True, exist_ok=True)
    if any(out.glob("[ab]*.txt")):
        raise typer.BadParameter(f"{out} already holds runs: give an empty folder")
    path = os.environ.get("PYTHONPATH", "")
    trees = {tree: ([sys.executable, str(root / "scripts" / "fem_phase_profile.py")],
                    {"PYTHONPATH": os.pathsep.join(p for p in (str(root), path) if p)})
             for tree, root in (("b", before_root), ("a", REPO))}
    for k in range(1, pairs + 1):
        for tree in ("b", "a") if k % 2 else ("a", "b"):
            command, env = trees[tree]
            result = subprocess.run([*command, *(profile_args or [])], cwd=REPO, env=os.environ | env,
                                    capture_output=True, text=True)
            log = out / f"{tree}{k}.txt"
            log.write_text(result.stdout + result.stderr)
            name = "before" if tree == "b" else "after"
            try:
                if result.returncode:
                    raise ValueError(f"exit {result.returncode}")
                seconds = profile_summary(result.stdout)[0]
            except ValueError as error:
                print(f"the {name} tree's run {k} failed ({error}); its output: {log}", file=sys.stderr)
                raise typer.Exit(1) from None
            print(f"{tree}{k}: {seconds:.3f} s", flush=True)
    summarize(out)


@app.command()
def summarize(out: Path = typer.Argument(..., help="a folder of b<k>.txt and a<k>.txt runs")) -> None:
    """Each tree's median seconds and the after/before ratio of the pairs with its bootstrap interval."""
    try:
        summary = read_pairs(out)
    except ValueError as error:
        raise typer.BadParameter(str(error)) from None
    print("\n".join(summary.lines()))


if __name__ == "__main__":
    app()
