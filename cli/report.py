"""Presenting engine measurements: text tables, the JSON report file and PNG plots.

Formats what ``facecast.rig.evaluation.evaluate`` and the engine benchmark return; it must not
measure or compute anything itself (matplotlib only with the Agg backend, no windows).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # matplotlib loads when a figure is drawn
    from matplotlib.figure import Figure

__all__ = [
    "format_error_table",
    "format_timing_table",
    "json_safe",
    "plot_error_over_time",
    "save_frames_picture",
    "write_json",
]


def json_safe(value: object) -> object:
    """``value`` with numpy scalars/arrays as Python numbers/lists and NaN/Inf as None.

    Containers and numbers come back as what ``json.dumps`` writes; anything else as it is.
    """
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def write_json(path: str | os.PathLike[str], report: dict[str, Any]) -> Path:
    """Write ``report`` as indented JSON (NaN/Inf become null); returns the path."""
    out = Path(path)
    if out.parent and not out.parent.exists():
        raise FileNotFoundError(f"{out.parent}: no such folder for {out.name}")
    out.write_text(json.dumps(json_safe(report), indent=1, allow_nan=False) + "\n", "utf-8")
    return out


def _pct(value: float | None) -> str:
    if value is None or not math.isfinite(value):
        return "-"
    if value != 0 and abs(value) < 1e-3:
        return f"{value:.1e}"
    return f"{value:.3f}" if abs(value) < 100 else f"{value:.0f}"


def format_error_table(report: dict[str, Any]) -> str:
    """The error table of an ``evaluate`` report: one row per method, per condition.

    Columns: eq. 4.1 x/y/z %, RMS % and max % of the bounding-box diagonal.
    """
    errors = report.get("errors")
    if not errors:
        return "no ground truth: error table skipped"
    labels = list(report["methods"])
    width = max(len(label) for label in labels) + 2
    conditions = list(errors)
    head = f"{'method':<{width}}" + "".join(
        f"| {c + (' (noise ' + format(report['noise'], 'g') + ')' if c == 'noisy' else ''):<53}"
        for c in conditions
    )
    sub = f"{'':<{width}}" + "".join(
        f"| {'x %':>8}{'y %':>8}{'z %':>8}{'RMS %':>9}{'max %':>9}{'jitter':>9}  "
        for _ in conditions
    )
    lines = [
        "Cloning error (thesis eq. 4.1 per axis; RMS and max of the bounding-box diagonal; "
        "jitter: RMS 2nd difference of the cloned vertices, % of the diagonal per frame^2)",
        head,
        sub,
        "-" * len(sub),
    ]
    for label in labels:
        failed = report["methods"][label].get("failed")
        row = f"{label:<{width}}"
        for condition in conditions:
            entry = errors[condition].get(label)
            if entry is None:
                row += f"| {'failed: ' + (failed or '?'):<53.53}"
                continue
            eq = entry["eq41_percent"]
            row += (
                f"| {_pct(eq['x']):>8}{_pct(eq['y']):>8}{_pct(eq['z']):>8}"
                f"{_pct(entry['rms_percent']):>9}{_pct(entry['max_percent']):>9}"
                f"{_pct(entry.get('jitter_percent')):>9}  "
            )
        lines.append(row)
    return "\n".join(lines)


def _duration(seconds: float | None) -> str:
    if seconds is None:
        return "-"
    if seconds < 1e-3:
        return f"{seconds * 1e6:.2f} us"
    if seconds < 1.0:
        return f"{seconds * 1e3:.2f} ms"
    return f"{seconds:.2f} s"


def format_timing_table(timing: dict[str, Any] | None, *, num_examples: int | None = None) -> str:
    """The thesis's Table 4.4 from ``evaluate``'s ``timing``."""
    if not timing:
        return "timing not measured"
    rows = [
        ("rig", str(timing.get("rig", ""))),
        ("number of frames", str(timing["num_frames"])),
        ("number of example models", "-" if num_examples is None else str(num_examples)),
        ("time for defining weight functions (fit)", _duration(timing["fit_seconds"])),
        ("total weight extraction time (one batch)", _duration(timing["weights_total_seconds"])),
        ("weights per frame, batched", _duration(timing["weights_batched_per_frame_seconds"])),
        ("weights per frame, one at a time", _duration(timing["weights_single_seconds"])),
        ("blending per frame, one at a time", _duration(timing["blend_single_seconds"])),
        ("blending per frame, batched", _duration(timing["blend_batched_per_frame_seconds"])),
        ("frames per second (weights + blend, one at a time)",
         f"{timing['frames_per_second']:.0f}"),
    ]  # fmt: skip
    width = max(len(name) for name, _ in rows) + 2
    return "\n".join(
        ["Computation time (thesis Table 4.4)"] + [f"  {n:<{width}}{v}" for n, v in rows]
    )


def _figure(width: float, height: float) -> Figure:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(width, height), dpi=100)
    FigureCanvasAgg(figure)
    return figure


def plot_error_over_time(
    path: str | os.PathLike[str],
    report: dict[str, Any],
    *,
    fps: float,
    labels: Sequence[str] | None = None,
) -> Path | None:
    """PNG of the per-frame eq. 4.1 error (mean of the three axes) for each method.

    One panel per condition (clean, noisy), log scale; needs the report's series.
    """
    errors = report.get("errors")
    if not errors:
        return None
    conditions = list(errors)
    figure = _figure(10, 3.2 * len(conditions))
    for row, condition in enumerate(conditions):
        axes = figure.add_subplot(len(conditions), 1, row + 1)
        for label, entry in errors[condition].items():
            if labels is not None and label not in labels:
                continue
            series = entry.get("per_frame")
            if series is None:
                continue
            values = np.asarray(series["eq41_percent"], dtype=float).mean(axis=1)
            times = np.arange(values.size) / fps
            axes.plot(times, np.maximum(values, 1e-12), label=label, linewidth=1.0)
        axes.set_yscale("log")
        axes.set_ylabel("eq. 4.1 error, %")
        title = condition if condition == "clean" else f"{condition} (noise {report['noise']:g})"
        axes.set_title(title)
        axes.grid(True, which="major", alpha=0.3)
        axes.legend(fontsize=7, ncol=2, loc="upper right")
    axes.set_xlabel("time, s")
    figure.tight_layout()
    figure.savefig(str(path))
    return Path(path)


def save_frames_picture(
    path: str | os.PathLike[str],
    panels: Sequence[Sequence[tuple[str, np.ndarray, np.ndarray]]],
    *,
    title: str | None = None,
) -> Path:
    """PNG grid of meshes, one row per time: ``panels[row] = [(label, vertices, faces), ...]``.

    Drawn by ``facecast.cli.render.save_side_by_side``.
    """
    from facecast.cli.render import save_side_by_side

    return save_side_by_side(
        path, [list(row) for row in panels], title=title, panel_size=(260, 260)
    )


def plot_jitter_against_lag(
    path: str | os.PathLike[str], tradeoff: dict[str, Any], *, title: str | None = None
) -> Path:
    """PNG of ``rig.temporal.temporal_tradeoff``: jitter against lag, one line per family.

    The one-frame lag is marked; the raw (unfiltered) clone and the truth's own jitter are
    drawn for reference.
    """
    figure = _figure(8, 5)
    axes = figure.add_subplot(1, 1, 1)
    rows = tradeoff["rows"]
    markers = {"one-euro": "o", "kalman": "s", "rts": "^"}
    for family, marker in markers.items():
        points = sorted(
            (r["lag_frames"], r["jitter"], r["label"]) for r in rows if r["family"] == family
        )
        if not points:
            continue
        lags, jitters, _ = zip(*points, strict=True)
        # Kalman and RTS settings are one knob (a curve); one-euro's are a grid (points).
        axes.plot(lags, jitters, marker=marker, linewidth=0.0 if family == "one-euro" else 0.8,
                  label=family)  # fmt: skip
        for lag, jitter, label in points:
            short = label.replace("one-euro ", "").replace("Kalman, acceleration ", "a=")
            short = short.replace("RTS, acceleration ", "a=")
            short = short.replace(" noise/s^2", "σ")
            axes.annotate(short, (lag, jitter), fontsize=6, xytext=(3, 3),
                          textcoords="offset points")  # fmt: skip
    raw = [r for r in rows if r["family"] == "raw"]
    if raw:
        axes.axhline(raw[0]["jitter"], color="grey", linestyle=":", label="raw (no filter)")
    axes.axhline(tradeoff["truth_jitter"], color="black", linestyle="--", label="truth")
    axes.axvline(1.0, color="red", linewidth=0.8, label="one frame")
    far = max((r["lag_frames"] for r in rows), default=0.0)
    if far > 6.0:
        axes.set_xlim(-2.2, 6.0)
        axes.text(0.99, 0.02, f"settings lagging more than 6 frames (up to {far:.1f}) off "
                  "the plot", transform=axes.transAxes, ha="right", fontsize=7)  # fmt: skip
    axes.set_xlabel("lag behind the ideal clone, frames (negative: ahead)")
    axes.set_ylabel("jitter, % of the diagonal per frame^2")
    axes.set_yscale("log")
    axes.grid(True, which="both", alpha=0.3)
    axes.legend(fontsize=8)
    if title:
        axes.set_title(title, fontsize=9)
    figure.tight_layout()
    figure.savefig(str(path))
    return Path(path)
