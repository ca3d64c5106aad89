"""``transtac-sim sweep``: calls ``transtac_sim.sweep.run.run_sweep`` and prints its report; bad input ends
with one red line naming the file and key."""

from __future__ import annotations

import time
from pathlib import Path

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

console = Console()


def register(app: typer.Typer) -> None:
    @app.command()
    def sweep(sweep_file: Path = typer.Argument(..., help="sweep file, e.g. scenes/sweeps/marker_density.toml"),
              out: Path = typer.Option(..., "--out", help="sweep folder (created; an unfinished sweep is resumed)"),
              workers: int = typer.Option(1, min=1, help="parallel tasks (processes, or Ray CPUs)"),
              executor: str = typer.Option("local", help="local | ray"),
              address: str = typer.Option(None, help="Ray cluster address (default: start a local Ray)")) -> None:
        """Design-space sweep of marker layouts (and gel, stiffness, baseline): per point a benchmark set is
        simulated, rendered, run through the pipeline and scored; writes results.csv, plots and report.html."""
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

        from transtac_sim.config import ConfigError
        from transtac_sim.sweep.run import run_sweep

        t0 = time.perf_counter()
        bar = Progress(TextColumn("[bold]{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                       TimeElapsedColumn(), TimeRemainingColumn(), console=console)
        tasks: dict[str, int] = {}

        def progress(stage: str, done: int, total: int) -> None:
            if not tasks:
                bar.start()  # only once the input is checked: bad input prints its one line alone
            if stage not in tasks:
                tasks[stage] = bar.add_task(stage, total=max(total, 1))
            bar.update(tasks[stage], completed=done if total else 1, total=max(total, 1))

        try:
            try:
                rep = run_sweep(sweep_file, out, workers=workers, executor=executor, address=address, progress=progress)
            finally:
                if tasks:
                    bar.stop()
        except (ConfigError, ValueError) as e:
            console.print("[bold red]error:[/] " + escape(str(e).replace("invalid configuration\n  ", "")), soft_wrap=True)
            raise typer.Exit(2) from None
        tab = Table(title=f"sweep {rep.root}", show_header=False)
        tab.add_row("points", f"{rep.done} done ({rep.resumed} already there), {len(rep.failed)} failed")
        for f in rep.failed[:5]:
            tab.add_row("  failed", escape(f"{f['point']}: {f['reason']}"))
        tab.add_row("FEM", f"{rep.fem_solves} solved now, {rep.fem_cached} from the cache, {rep.fem_shared} "
                           "(point, motion) pairs reused another point's solve")
        tab.add_row("images", f"{rep.renders} set(s) rendered, {rep.render_shared} point(s) scored another point's images")
        tab.add_row("table", str(rep.table))
        tab.add_row("report", str(rep.report_html))
        tab.add_row("total", f"{time.perf_counter() - t0:.1f} s")
        console.print(tab)
        if rep.failed:
            raise typer.Exit(1)
