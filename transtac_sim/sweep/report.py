"""A sweep's results for a person: ``results.csv`` (one row per point), a plot of each metric against each
swept parameter, the Pareto front of reconstruction error against marker count, and ``report.md`` /
``report.html`` (open the HTML in a browser; the plots sit beside it in ``plots/``)."""

from __future__ import annotations

import html
import math
from pathlib import Path

import numpy as np

METRICS = {
    "detection_recall": "detection recall (2 px)",
    "detection_precision": "detection precision (2 px)",
    "correct_matches_per_frame": "correct stereo matches / frame",
    "match_precision": "match precision",
    "tracking_idf1": "tracking IDF1 (left view)",
    "reconstruction_error_mm": "reconstruction error, median (mm)",
}
COSTS = ("fem_seconds", "render_seconds", "seconds_detect_per_frame", "seconds_track_per_frame",
         "seconds_match_per_frame", "seconds_triangulate_per_frame")


def pareto_front(markers: np.ndarray, error: np.ndarray) -> np.ndarray:
    """Indices of the points no other point beats on both: more markers (denser sampling of the surface)
    and a lower reconstruction error; sorted by marker count."""
    ok = np.flatnonzero(np.isfinite(error))
    front = [i for i in ok if not any((markers[j] >= markers[i] and error[j] <= error[i]) and
                                      (markers[j] > markers[i] or error[j] < error[i]) for j in ok)]
    return np.array(sorted(front, key=lambda i: markers[i]), dtype=int)


def _plot_parameter(df, param: str, group_by: list[str], path: Path) -> Path:
    """Each metric against ``param``, one line per combination of the other swept parameters."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(13, 7))
    groups = [(None, df)] if not group_by else list(df.groupby(group_by, sort=True))
    for ax, (m, title) in zip(axes.ravel(), METRICS.items(), strict=True):
        for value, g in groups:
            g = g.sort_values(param)
            values = value if isinstance(value, tuple) else (value,)
            label = None if value is None else ", ".join(f"{k} = {v}" for k, v in zip(group_by, values, strict=True))
            ax.plot(g[param], g[m], "o-", label=label)
        ax.set_xlabel(param)
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
    if group_by:
        axes[0, 0].legend(fontsize=7)
    fig.suptitle(f"metrics against {param}")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _plot_pareto(df, front: np.ndarray, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    ax.scatter(df["markers"], df["reconstruction_error_mm"], c="grey", label="points")
    f = df.iloc[front]
    ax.plot(f["markers"], f["reconstruction_error_mm"], "o-", color="C3", label="Pareto front")
    for _, r in f.iterrows():
        ax.annotate(r["point"], (r["markers"], r["reconstruction_error_mm"]), fontsize=7, xytext=(3, 3),
                    textcoords="offset points")
    ax.set_xlabel("markers in the gel")
    ax.set_ylabel("reconstruction error, median (mm)")
    ax.set_title("reconstruction error against marker count")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _fmt(v) -> str:
    import pandas as pd

    if v is None or v is pd.NA:
        return ""
    if isinstance(v, float):
        return "nan" if math.isnan(v) else f"{v:.4g}"
    return str(v)


def write_report(root: Path, sweep, rows: list[dict], reuse: dict) -> tuple[Path, Path, Path, list[Path]]:
    """Write results.csv, the plots, report.md and report.html into ``root``."""
    import pandas as pd

    df = pd.DataFrame(rows)
    for c in ("markers", "frames", "count"):
        if c in df:
            df[c] = df[c].astype("Int64")  # whole numbers, empty for a failed point
    table = root / "results.csv"
    df.to_csv(table, index=False)
    ok = df[df["status"] == "done"].reset_index(drop=True) if "status" in df else df.iloc[:0]
    plots: list[Path] = []
    numeric = [p for p in sweep.swept if p not in ("pattern", "detector", "matcher")]
    categorical = [p for p in sweep.swept if p in ("pattern", "detector", "matcher")]
    front = np.zeros(0, int)
    if len(ok):
        xs = ["markers" if p in ("count", "density_per_mm2") else p for p in numeric] or ["markers"]
        for x in dict.fromkeys(xs):
            others = [p for p in sweep.swept if p != x and not (x == "markers" and p in ("count", "density_per_mm2"))]
            plots.append(_plot_parameter(ok, x, others, root / "plots" / f"metrics_vs_{x}.png"))
        front = pareto_front(ok["markers"].to_numpy(float), ok["reconstruction_error_mm"].to_numpy(float))
        plots.append(_plot_pareto(ok, front, root / "plots" / "pareto_error_vs_markers.png"))
    cols = ["point", *sweep.swept, "markers", *METRICS, "fem_seconds", "render_seconds", "seconds_detect_per_frame"]
    cols = [c for c in dict.fromkeys(cols) if c in df]
    b = sweep.file.benchmark
    motions = ", ".join(f"{m.kind} ({m.indenter})" for m in b.motions)
    md = [f"# Sweep `{sweep.file.name}`", "",
          f"{len(df)} points ({', '.join(sweep.swept) or 'nothing'} varied; categorical: {', '.join(categorical) or 'none'}), "
          f"each scored on {len(b.motions)} motions x {b.frames} frames: {motions}; press depth {b.press_depth_mm} mm. "
          f"Sweep file: `{sweep.path}`.", "",
          "## What was reused", "",
          f"- FEM: the {reuse['points']} points x {reuse['motions']} motions = {reuse['fem_pairs_total']} (point, motion) pairs "
          f"needed {reuse['fem_solves_total']} FEM solve(s): {reuse['fem_pairs_total'] - reuse['fem_solves_total']} pair(s) "
          "reused a solve of another point (markers are embedded after the solve, so points that differ only in their "
          f"markers or cameras share it). This run: {reuse['fem_solves_run']} solved, {reuse['fem_solves_from_cache']} "
          "found in the cache.",
          f"- Images: the {reuse['points']} points needed {reuse['image_sets_total']} image set(s) of {reuse['frames_per_set']} "
          f"stereo frames: {reuse['points_sharing_images_total']} point(s) scored images rendered for another point (they "
          f"differ only in pipeline settings). This run: {reuse['frames_rendered_now']} frame(s) rendered, the others were "
          "already on disk.",
          f"- Resume: {reuse['resumed_points']} point(s) already had their result and were not recomputed.", "",
          "## Results", "",
          "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    md += ["| " + " | ".join(_fmt(r[c]) for c in cols) + " |" for r in df.to_dict("records")]
    failed = df[df["status"] != "done"] if "status" in df else df.iloc[:0]
    if len(failed):
        md += ["", "## Failed points", ""] + [f"- {r['point']}: {r['reason']}" for r in failed.to_dict("records")]
    if len(front):
        md += ["", "## Pareto front: reconstruction error against marker count", "",
               "Points no other point beats with both more markers and a lower median reconstruction error:", ""]
        md += [f"- {r['point']}: {int(r['markers'])} markers, {r['reconstruction_error_mm']:.4f} mm"
               + "".join(f", {p} = {r[p]}" for p in sweep.swept if p != "count") for r in ok.iloc[front].to_dict("records")]
        best = ok.iloc[int(np.nanargmax(ok["correct_matches_per_frame"].to_numpy(float)))]
        md += ["", f"Most correct matches per frame: {best['point']} ({best['correct_matches_per_frame']:.1f} per frame, "
               f"{int(best['markers'])} markers, {best['reconstruction_error_mm']:.4f} mm)."]
    for param in sweep.swept if len(ok) else []:
        means = ok.groupby(param, sort=True)[["markers", *METRICS]].mean(numeric_only=True)
        md += ["", f"## Against {param} (mean over the other parameters)", "",
               f"| {param} | " + " | ".join(["markers", *METRICS]) + " |", "|---" * (len(METRICS) + 2) + "|"]
        md += [f"| {v} | " + " | ".join(_fmt(float(r[c])) for c in ["markers", *METRICS]) + " |" for v, r in means.iterrows()]
    md += ["", "## Plots", ""] + [f"![{p.stem}](plots/{p.name})" for p in plots]
    md += ["", "Metrics: scripts/bench_detection.py, bench_tracking.py and bench_reconstruct.py's definitions "
           "(transtac_sim/sweep/scoring.py). Costs: fem_seconds is the time of the point's FEM solves when they were "
           "solved (shared between points), render_seconds the render and camera time of its image set; per-frame "
           "pipeline times in results.csv."]
    md_path = root / "report.md"
    md_path.write_text("\n".join(md) + "\n")
    html_path = root / "report.html"
    html_path.write_text(_html(md))
    return table, md_path, html_path, plots


def _html(md_lines: list[str]) -> str:
    """The Markdown report as a self-contained HTML page (tables, lists, images, headings)."""
    out, in_table, in_list = [], False, False
    for line in md_lines:
        if line.startswith("|"):
            if line.startswith("|---"):
                continue
            cells = [html.escape(c.strip()) for c in line.strip("|").split("|")]
            tag = "th" if not in_table else "td"
            if not in_table:
                out.append("<table>")
                in_table = True
            out.append("<tr>" + "".join(f"<{tag}>{c}</{tag}>" for c in cells) + "</tr>")
            continue
        if in_table:
            out.append("</table>")
            in_table = False
        if line.startswith("- "):
            if not in_list:
                out.append("<ul>")
                in_list = True
            out.append(f"<li>{html.escape(line[2:])}</li>")
            continue
        if in_list:
            out.append("</ul>")
            in_list = False
        if line.startswith("!["):
            src = line[line.index("(") + 1 : -1]
            out.append(f'<p><img src="{html.escape(src)}" style="max-width:100%"></p>')
        elif line.startswith("## "):
            out.append(f"<h2>{html.escape(line[3:])}</h2>")
        elif line.startswith("# "):
            out.append(f"<h1>{html.escape(line[2:])}</h1>")
        elif line:
            out.append(f"<p>{html.escape(line)}</p>")
    if in_table:
        out.append("</table>")
    if in_list:
        out.append("</ul>")
    style = ("body{font-family:sans-serif;max-width:1200px;margin:2em auto}table{border-collapse:collapse;font-size:12px}"
             "td,th{border:1px solid #ccc;padding:3px 6px}th{background:#eee}")
    return f"<!doctype html><html><head><meta charset='utf-8'><title>sweep report</title><style>{style}</style></head><body>\n" + \
        "\n".join(out) + "\n</body></html>\n"
