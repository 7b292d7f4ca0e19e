"""The campaign report of ``magcal batch``: ``report.csv`` and a self-contained ``report.html``.

One row per recording (:data:`COLUMNS`): sets, drops, time span, the TMI residual
``| |B| - F |`` (median and 95th percentile, T and in units of the calibration's noise),
the tensor noise and the calibration used. The HTML page adds, per vehicle, the trend of
those over the recordings' start times as inline SVG charts (no external file, script or
font), so a calibration drifting between missions shows at a glance: with Gaussian noise
of standard deviation ``s`` per axis a calibration that holds gives a median near
``0.67 s`` and a 95th percentile near ``1.96 s`` (the dashed noise-floor lines). The charts'
value axes are logarithmic, so one recording a thousand times above the floor does not
flatten the others onto it, and a recording whose median is more than :data:`FLAG_RATIO`
noise sd is flagged (dotted line, ``flag`` column, a list at the top of the page). Files a
walk met that are not recordings are listed as skipped. Every number in the page's tables
carries its exact value in a ``data-value`` attribute.
"""

from __future__ import annotations

import csv
import html
import io
import json
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

from magcal_ros.app.campaign import Outcome
from magcal_ros.core.stamps import format_seconds, ns_to_seconds
from magcal_ros.core.units import NT
from magcal_ros.io.atomic import atomic_path

COLUMNS: tuple[str, ...] = (
    "recording", "vehicle", "status", "start", "end", "start_utc", "duration_s", "sets", "drops",
    "intensity_T", "noise_T", "tmi_median_T", "tmi_p95_T", "tmi_median_noise", "tmi_p95_noise",
    "tensor_noise_T_per_m", "calibration", "input", "output", "seconds", "worker", "reason", "notes", "flag",
)
"""Columns of ``report.csv`` (times in decimal seconds, exact; fields in T, gradients in T/m)."""

GAUSSIAN_MEDIAN = 0.6745
"""Median of ``|x|`` for a standard normal ``x``: the TMI residual of a calibration that holds, in noise units."""
GAUSSIAN_P95 = 1.96
"""95th percentile of ``|x|`` for a standard normal ``x``."""
FLAG_RATIO = 5.0
"""A recording whose median TMI residual exceeds this many noise sd (7.4 times what a calibration that
holds gives with Gaussian noise) is flagged: its calibration does not hold for it (drift, a new
payload, the wrong calibration) or its survey saw a field far from F."""


def flag_of(o: Outcome) -> str:
    """Why a recording is flagged ('' when it is not): its median TMI residual over :data:`FLAG_RATIO`."""
    ratio = o.ratio(o.tmi_median)
    if o.other or o.status == "failed" or ratio is None or ratio <= FLAG_RATIO:
        return ""
    return f"TMI median {ratio:.3g}x the noise: far above the floor (flagged over {FLAG_RATIO:g}x)"


def _utc(stamp_ns: int | None, seconds: bool = True) -> str:
    if stamp_ns is None:
        return ""
    t = datetime.fromtimestamp(float(ns_to_seconds(stamp_ns)), tz=timezone.utc)
    return t.strftime("%Y-%m-%dT%H:%M:%SZ" if seconds else "%Y-%m-%d %H:%M")


def _duration(o: Outcome) -> float | None:
    return None if o.start_ns is None or o.end_ns is None else (o.end_ns - o.start_ns) * 1e-9


def values(o: Outcome) -> dict[str, object]:
    """A recording's report row, :data:`COLUMNS` to values (None: unknown)."""
    return {
        "recording": o.name, "vehicle": o.vehicle, "status": o.status,
        "start": o.start_ns, "end": o.end_ns, "start_utc": _utc(o.start_ns), "duration_s": _duration(o),
        "sets": o.sets, "drops": o.drops, "intensity_T": o.intensity, "noise_T": o.noise,
        "tmi_median_T": o.tmi_median, "tmi_p95_T": o.tmi_p95,
        "tmi_median_noise": o.ratio(o.tmi_median), "tmi_p95_noise": o.ratio(o.tmi_p95),
        "tensor_noise_T_per_m": o.tensor_noise, "calibration": o.calibration, "input": o.input, "output": o.output,
        "seconds": o.seconds, "worker": o.worker, "reason": o.reason, "notes": "; ".join(o.notes),
        "flag": flag_of(o),
    }


def _csv_text(key: str, value: object) -> str:
    if value is None:
        return ""
    if key in ("start", "end"):
        return format_seconds(int(value))  # type: ignore[call-overload]
    if isinstance(value, float):
        return f"{value:.9g}"
    return str(value)


def ordered(outcomes: Sequence[Outcome]) -> list[Outcome]:
    """Recordings by vehicle, then start time (unknown last), then name; files that are none last."""
    return sorted(outcomes, key=lambda o: (o.other, o.vehicle, o.start_ns is None, o.start_ns or 0, o.name))


def write_csv(path: str | os.PathLike[str], outcomes: Sequence[Outcome]) -> None:
    """``report.csv``, written atomically."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(COLUMNS)
    for o in ordered(outcomes):
        row = values(o)
        w.writerow([_csv_text(k, row[k]) for k in COLUMNS])
    with atomic_path(path) as tmp:
        tmp.write_text(buf.getvalue(), encoding="utf-8")


# --------------------------------------------------------------------------- HTML

PALETTE = ("#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf", "#bcbd22", "#7f7f7f")

CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',Roboto,sans-serif;margin:1.5em;color:#222;max-width:1400px}
h1{margin-bottom:.2em} .summary{color:#444} .failed{color:#b00}
table{border-collapse:collapse;font-size:13px;margin:.5em 0 1.5em}
th,td{border:1px solid #ccc;padding:3px 6px;text-align:right;white-space:nowrap}
th{background:#f3f3f3;cursor:pointer;position:sticky;top:0} td.text{text-align:left}
tr.failed td{background:#fdecec} tr.skipped td{color:#555} tr.flagged td{background:#fff4d6}
.flagged{color:#8a5a00}
.charts{display:flex;flex-wrap:wrap;gap:12px} .chart{border:1px solid #ddd;background:#fff}
.muted{color:#666;font-size:13px}
"""

SCRIPT = """
(function(){
  function key(td){var v=td.getAttribute('data-value');if(v===null||v===''){return null}
    var x=Number(v);return isNaN(x)?v.toLowerCase():x}
  document.querySelectorAll('table.sortable').forEach(function(table){
    table.querySelectorAll('th').forEach(function(th,i){
      th.title='sort';th.addEventListener('click',function(){
        var body=table.tBodies[0],rows=Array.prototype.slice.call(body.rows);
        var dir=th.getAttribute('data-dir')==='asc'?-1:1;th.setAttribute('data-dir',dir>0?'asc':'desc');
        rows.sort(function(a,b){var x=key(a.cells[i]),y=key(b.cells[i]);
          if(x===y){return 0} if(x===null){return 1} if(y===null){return -1} return x<y?-dir:dir});
        rows.forEach(function(r){body.appendChild(r)});
      });
    });
  });
  var rows=document.querySelectorAll('#recordings tbody tr').length;
  document.documentElement.setAttribute('data-ready', String(rows));
})();
"""


def _fmt(value: object, scale: float = 1.0, digits: int = 3) -> str:
    if value is None:
        return "-"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        v = value / scale
        return f"{v:.{digits}g}" if abs(v) < 10 ** digits else f"{v:.0f}"
    return str(value)


def _cell(key: str, value: object, shown: str, text: bool = False, title: str = "") -> str:
    exact = "" if value is None else (repr(value) if isinstance(value, float) else str(value))
    cls = ' class="text"' if text else ""
    tip = f' title="{html.escape(title)}"' if title else ""
    return f'<td data-key="{key}" data-value="{html.escape(exact)}"{cls}{tip}>{html.escape(shown)}</td>'


RECORDING_COLUMNS: tuple[tuple[str, str, Callable[[Outcome], tuple[object, str]]], ...] = (
    ("recording", "recording", lambda o: (o.name, o.name)),
    ("vehicle", "vehicle", lambda o: (o.vehicle, o.vehicle or "-")),
    ("status", "status", lambda o: (o.status, o.status)),
    ("start", "start (UTC)", lambda o: (o.start_ns, _utc(o.start_ns) or "-")),
    ("duration_s", "duration s", lambda o: (_duration(o), _fmt(_duration(o), digits=4))),
    ("sets", "sets", lambda o: (o.sets, _fmt(o.sets))),
    ("drops", "drops", lambda o: (o.drops, _fmt(o.drops))),
    ("noise_T", "noise nT", lambda o: (o.noise, _fmt(o.noise, NT))),
    ("tmi_median_T", "TMI median nT", lambda o: (o.tmi_median, _fmt(o.tmi_median, NT))),
    ("tmi_p95_T", "TMI p95 nT", lambda o: (o.tmi_p95, _fmt(o.tmi_p95, NT))),
    ("tmi_median_noise", "median / noise", lambda o: (o.ratio(o.tmi_median), _fmt(o.ratio(o.tmi_median)))),
    ("tmi_p95_noise", "p95 / noise", lambda o: (o.ratio(o.tmi_p95), _fmt(o.ratio(o.tmi_p95)))),
    ("tensor_noise_T_per_m", "tensor noise nT/m", lambda o: (o.tensor_noise, _fmt(o.tensor_noise, NT))),
    ("calibration", "calibration", lambda o: (o.calibration, Path(o.calibration).name if o.calibration else "-")),
    ("reason", "reason / notes", lambda o: (o.reason or "; ".join(o.notes), o.reason or "; ".join(o.notes))),
    ("flag", "flag", lambda o: (flag_of(o), flag_of(o))),
)
TEXT_KEYS = {"recording", "vehicle", "status", "start", "calibration", "reason", "flag"}


CHART_WIDTH, CHART_HEIGHT = 460, 270
"""Size of a chart (px)."""
MARGINS = (58, 14, 28, 62)
"""Left, right, top and bottom margins of a chart's plot area (px): the value axis's labels, the time
axis's two-line labels and the legend fit in them."""
CHAR_WIDTH = 6.5
"""Generous width (px) of a character of the charts' 10 px sans-serif text, to space labels apart."""


@dataclass(frozen=True)
class Reference:
    """A horizontal line across a chart: the noise floor (dashed) or the flag threshold (dotted)."""

    value: float
    label: str
    kind: str = "floor"


def log_range(values: Sequence[float]) -> tuple[int, int]:
    """Whole decades ``(lo, hi)``, ``lo < hi``, that hold every positive value (10^lo .. 10^hi)."""
    logs = [math.log10(v) for v in values if v > 0 and math.isfinite(v)]
    if not logs:
        return 0, 1
    lo, hi = math.floor(min(logs)), math.ceil(max(logs))
    return lo, max(hi, lo + 1)


def _decade_ticks(lo: int, hi: int) -> list[float]:
    """Value-axis ticks: every decade, and 2 and 5 within each when at most two decades are shown."""
    ticks = [10.0**k for k in range(lo, hi + 1)]
    if hi - lo <= 2:
        ticks += [m * 10.0**k for k in range(lo, hi) for m in (2.0, 5.0)]
    return sorted(ticks)


def time_labels(t0: int, t1: int, width: float) -> list[tuple[int, str, str, str]]:
    """Time-axis labels of a plot ``width`` px wide from ``t0`` to ``t1`` (ns): ``(stamp, anchor, date,
    time of day UTC)``, as many as fit side by side with room between them (two to five)."""
    text, gap = CHAR_WIDTH * len("2025-05-01"), 16.0  # the wider line of a label; room between two
    count = 5
    # the end labels hang inwards from their ticks (anchored start / end), the others are centred on theirs
    while count > 2 and width / (count - 1) < 1.5 * text + gap:
        count -= 1
    out = []
    for i in range(count):
        t = t0 + (t1 - t0) * i // (count - 1)
        anchor = "start" if i == 0 else "end" if i == count - 1 else "middle"
        out.append((t, anchor, _utc(t, seconds=False)[:10], _utc(t, seconds=False)[11:]))
    return out


def _frame(title: str, unit: str, lo: int, hi: int) -> tuple[list[str], Callable[[float], float]]:
    """A chart's opening, plot frame, value axis (log) and unit; the value-to-y map."""
    w, h = CHART_WIDTH, CHART_HEIGHT
    left, right, top, bottom = MARGINS
    pw, ph = w - left - right, h - top - bottom

    def y(v: float) -> float:
        clipped = min(max(v, 10.0**lo), 10.0**hi) if v > 0 else 10.0**lo
        return top + ph * (1 - (math.log10(clipped) - lo) / (hi - lo))

    out = [f'<svg class="chart" xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" viewBox="0 0 {w} {h}" '
           f'data-title="{html.escape(title)}" data-scale="log" data-lo="{lo}" data-hi="{hi}" '
           f'data-top="{top}" data-height="{ph}">',
           f'<text x="{w / 2}" y="17" text-anchor="middle" font-size="13" font-weight="bold">{html.escape(title)}</text>',
           f'<rect x="{left}" y="{top}" width="{pw}" height="{ph}" fill="none" stroke="#bbb"/>']
    for v in _decade_ticks(lo, hi):
        major = abs(math.log10(v) - round(math.log10(v))) < 1e-9
        out.append(f'<line x1="{left}" x2="{left + pw}" y1="{y(v):.1f}" y2="{y(v):.1f}" '
                   f'stroke="{"#e4e4e4" if major else "#f3f3f3"}"/>'
                   f'<text class="tick" x="{left - 4}" y="{y(v) + 3.5:.1f}" text-anchor="end" font-size="10">{v:g}</text>')
    out.append(f'<text x="14" y="{top + ph / 2}" transform="rotate(-90 14 {top + ph / 2})" text-anchor="middle" '
               f'font-size="11">{html.escape(unit)} (log)</text>')
    return out, y


def svg_chart(title: str, unit: str, series: dict[str, list[tuple[int, float, str]]],
              colours: dict[str, str], references: Sequence[Reference] = ()) -> str:
    """A line chart (inline SVG) with a logarithmic value axis: per vehicle, ``(start ns, value, label)``
    points joined in time order; ``references`` drawn across it, labelled."""
    w, h = CHART_WIDTH, CHART_HEIGHT
    left, right, top, bottom = MARGINS
    pw, ph = w - left - right, h - top - bottom
    pts = [(t, v) for s in series.values() for t, v, _ in s if v is not None and math.isfinite(v)]
    if not pts:
        return (f'<svg class="chart" xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" viewBox="0 0 {w} {h}" '
                f'data-title="{html.escape(title)}">\n<text x="{w / 2}" y="17" text-anchor="middle" font-size="13" '
                f'font-weight="bold">{html.escape(title)}</text>\n<text x="{w / 2}" y="{h / 2}" text-anchor="middle" '
                'font-size="12" fill="#888">no data</text></svg>')
    t0, t1 = min(p[0] for p in pts), max(p[0] for p in pts)
    if t1 == t0:
        t0, t1 = t0 - 3600 * 10**9, t1 + 3600 * 10**9
    lo, hi = log_range([p[1] for p in pts] + [r.value for r in references])
    out, y = _frame(title, unit, lo, hi)

    def x(t: int) -> float:
        return left + pw * (t - t0) / (t1 - t0)

    for t, anchor, day, clock in time_labels(t0, t1, pw):
        out.append(f'<text class="time" x="{x(t):.1f}" y="{top + ph + 13}" text-anchor="{anchor}" font-size="10">'
                   f'<tspan x="{x(t):.1f}">{day}</tspan><tspan x="{x(t):.1f}" dy="11">{clock}</tspan></text>')
    for ref in references:
        dash, colour = ("4 3", "#888") if ref.kind == "floor" else ("1 3", "#c0392b")
        out.append(f'<line class="{ref.kind}" x1="{left}" x2="{left + pw}" y1="{y(ref.value):.1f}" y2="{y(ref.value):.1f}" '
                   f'stroke="{colour}" stroke-dasharray="{dash}" data-value="{ref.value!r}"><title>{html.escape(ref.label)}'
                   f'</title></line><text class="reference" x="{left + pw - 3}" y="{y(ref.value) - 3:.1f}" '
                   f'text-anchor="end" font-size="9" fill="{colour}">{html.escape(ref.label)}</text>')
    out += _series(series, colours, unit, x, y)
    out.append("</svg>")
    return "\n".join(out)


def _series(series: dict[str, list[tuple[int, float, str]]], colours: dict[str, str], unit: str,
            x: Callable[[int], float], y: Callable[[float], float]) -> list[str]:
    """Each vehicle's line and points, and the legend in rows under the time axis."""
    out = []
    legend_x, legend_y = MARGINS[0], CHART_HEIGHT - 8
    for vehicle, points in series.items():
        good = sorted((t, v, lab) for t, v, lab in points if v is not None and math.isfinite(v))
        if not good:
            continue
        colour = colours[vehicle]
        line = " ".join(f"{x(t):.1f},{y(v):.1f}" for t, v, _ in good)
        out.append(f'<polyline class="trend" data-vehicle="{html.escape(vehicle)}" points="{line}" fill="none" '
                   f'stroke="{colour}" stroke-width="1.5"/>')
        for t, v, lab in good:
            out.append(f'<circle cx="{x(t):.1f}" cy="{y(v):.1f}" r="3.5" fill="{colour}" data-recording="{html.escape(lab)}" '
                       f'data-value="{v!r}"><title>{html.escape(lab)}: {v:.3g} {html.escape(unit)}</title></circle>')
        name = vehicle or "(no vehicle)"
        width = 14 + CHAR_WIDTH * len(name)
        if legend_x + width > CHART_WIDTH - MARGINS[1] and legend_x > MARGINS[0]:
            break  # no room left: the vehicle table names every vehicle
        out.append(f'<rect x="{legend_x}" y="{legend_y - 8}" width="9" height="9" fill="{colour}"/>'
                   f'<text class="legend" x="{legend_x + 12}" y="{legend_y}" font-size="10">{html.escape(name)}</text>')
        legend_x += width + 8
    return out


def _charts(done: list[Outcome]) -> str:
    vehicles = sorted({o.vehicle for o in done})
    colours = {v: PALETTE[i % len(PALETTE)] for i, v in enumerate(vehicles)}
    relative = all(o.noise for o in done if o.tmi_median is not None)
    charts = []
    for attr, label, ref in (("tmi_median", "TMI residual, median", GAUSSIAN_MEDIAN),
                             ("tmi_p95", "TMI residual, 95th percentile", GAUSSIAN_P95)):
        series: dict[str, list[tuple[int, float, str]]] = {v: [] for v in vehicles}
        for o in done:
            value = getattr(o, attr)
            if o.start_ns is not None and value is not None:
                series[o.vehicle].append((o.start_ns, o.ratio(value) if relative else value / NT, o.name))  # type: ignore[arg-type]
        refs = [Reference(ref, f"noise floor {ref:g}")] if relative else []
        if relative and attr == "tmi_median":
            refs.append(Reference(FLAG_RATIO, f"flagged above {FLAG_RATIO:g}", "flag"))
        charts.append(svg_chart(label, "x noise" if relative else "nT", series, colours, refs))
    series = {v: [] for v in vehicles}
    for o in done:
        if o.start_ns is not None and o.tensor_noise is not None:
            series[o.vehicle].append((o.start_ns, o.tensor_noise / NT, o.name))
    charts.append(svg_chart("tensor noise", "nT/m", series, colours))
    return '<div class="charts">\n' + "\n".join(charts) + "\n</div>"


def _trend(items: list[Outcome], get: Callable[[Outcome], float | None]) -> tuple[object, str]:
    vals = [v for v in (get(o) for o in items) if v is not None]
    if not vals:
        return None, "-"
    if len(vals) == 1:
        return vals[0], f"{vals[0]:.3g}"
    return vals[-1] / vals[0] if vals[0] else None, f"{vals[0]:.3g} → {vals[-1]:.3g}"


def _vehicle_table(done: list[Outcome], failed: list[Outcome]) -> str:
    rows = []
    for vehicle in sorted({o.vehicle for o in done} | {o.vehicle for o in failed}):
        items = [o for o in ordered(done) if o.vehicle == vehicle]
        cals = sorted({Path(o.calibration).name for o in items if o.calibration})
        cells = [
            _cell("vehicle", vehicle, vehicle or "(none)", text=True),
            _cell("recordings", len(items), str(len(items))),
            _cell("failed", sum(o.vehicle == vehicle for o in failed), str(sum(o.vehicle == vehicle for o in failed))),
            _cell("first", items[0].start_ns if items else None, _utc(items[0].start_ns) if items else "-", text=True),
            _cell("last", items[-1].start_ns if items else None, _utc(items[-1].start_ns) if items else "-", text=True),
            _cell("calibrations", ", ".join(cals), ", ".join(cals) or "-", text=True),
        ]
        for key, get in (("tmi_median_noise", lambda o: o.ratio(o.tmi_median)), ("tmi_p95_noise", lambda o: o.ratio(o.tmi_p95)),
                         ("tmi_median_T", lambda o: None if o.tmi_median is None else o.tmi_median / NT),
                         ("tensor_noise_T_per_m", lambda o: None if o.tensor_noise is None else o.tensor_noise / NT)):
            change, shown = _trend(items, get)
            cells.append(_cell(key, change, shown))
        rows.append(f'<tr data-vehicle="{html.escape(vehicle)}">' + "".join(cells) + "</tr>")
    head = ("<tr><th>vehicle</th><th>recordings</th><th>failed</th><th>first start</th><th>last start</th>"
            "<th>calibrations</th><th>median / noise, first → last</th><th>p95 / noise, first → last</th>"
            "<th>TMI median nT, first → last</th><th>tensor noise nT/m, first → last</th></tr>")
    return (f'<table id="vehicles" class="sortable"><thead>{head}</thead><tbody>\n' + "\n".join(rows)
            + "\n</tbody></table>")


def _recording_table(outcomes: list[Outcome]) -> str:
    head = "".join(f'<th data-key="{k}">{html.escape(label)}</th>' for k, label, _ in RECORDING_COLUMNS)
    rows = []
    for o in outcomes:
        cells = []
        for key, _, get in RECORDING_COLUMNS:
            value, shown = get(o)
            title = o.calibration if key == "calibration" else o.input if key == "recording" else ""
            cells.append(_cell(key, value, shown, text=key in TEXT_KEYS, title=title))
        cls = o.status + (" flagged" if flag_of(o) else "")
        rows.append(f'<tr class="{html.escape(cls)}" data-name="{html.escape(o.name)}">' + "".join(cells) + "</tr>")
    return (f'<table id="recordings" class="sortable"><thead><tr>{head}</tr></thead><tbody>\n' + "\n".join(rows)
            + "\n</tbody></table>")


def _listing(key: str, heading: str, items: Sequence[Outcome], text: Callable[[Outcome], str]) -> list[str]:
    """A titled list (``id`` ``key``) of recordings or files with one line each; nothing when empty."""
    if not items:
        return []
    return ([f'<h2 class="{key}">{html.escape(heading)}</h2><ul id="{key}" class="{key}">']
            + [f'<li data-name="{html.escape(o.name)}"><b>{html.escape(o.name)}</b>: {html.escape(text(o))}</li>'
               for o in items]
            + ["</ul>"])


def _summary(items: Sequence[Outcome], others: Sequence[Outcome], outdir: str, created: datetime | None) -> str:
    """The page's opening paragraph: the counts, where the outputs are, when."""
    corrected = sum(o.status == "corrected" for o in items)
    skipped = sum(o.status == "skipped" for o in items)
    failed = sum(o.status == "failed" for o in items)
    flagged = sum(bool(flag_of(o)) for o in items)
    when = (created or datetime.now(timezone.utc)).strftime("%Y-%m-%d %H:%M:%S UTC")
    more = (f" {len(others)} file{'s' if len(others) != 1 else ''} found that {'are' if len(others) != 1 else 'is'} "
            "not a recording: skipped." if others else "")
    return (f'<p class="summary" id="summary" data-recordings="{len(items)}" data-corrected="{corrected}" '
            f'data-skipped="{skipped}" data-failed="{failed}" data-flagged="{flagged}" data-others="{len(others)}">'
            f"{len(items)} recordings: {corrected} corrected, {skipped} skipped (done by an earlier run, unchanged), "
            f"{failed} failed; {flagged} flagged (median TMI residual over {FLAG_RATIO:g} noise sd).{more} Outputs "
            f"in <code>{html.escape(outdir)}</code> (every output a run wrote there and that is still as written); "
            f"written {when} by <code>magcal batch</code>.</p>")


def render_html(outcomes: Sequence[Outcome], outdir: str, created: datetime | None = None) -> str:
    """The report page as one self-contained HTML text."""
    items = ordered([o for o in outcomes if not o.other])
    others = ordered([o for o in outcomes if o.other])
    done = [o for o in items if o.status != "failed"]
    failed = [o for o in items if o.status == "failed"]
    parts = [
        "<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
        "<title>magcal batch report</title>", f"<style>{CSS}</style></head><body>",
        "<h1>Campaign report</h1>", _summary(items, others, outdir, created),
    ]
    parts += _listing("failed", "Failed", failed, lambda o: o.reason)
    parts += _listing("flagged", "Flagged: far above the noise floor", [o for o in items if flag_of(o)], flag_of)
    parts += [
        "<h2>Per vehicle over time</h2>",
        '<p class="muted">Each point is a recording at its first set\'s time, joined per vehicle, on logarithmic '
        "axes. TMI residual: <code>| |B| - F |</code> over every corrected vector, F the calibration's reference "
        "intensity, in units of the calibration's noise per axis; a calibration that holds stays near the dashed "
        "noise-floor lines (0.67 for the median, 1.96 for the 95th percentile with Gaussian noise), one that "
        f"drifts between missions climbs away from them; a median over {FLAG_RATIO:g} (dotted line) is flagged. "
        "Tensor noise: the set-to-set noise of the six measured gradient components.</p>",
        _charts(done), _vehicle_table(done, failed),
        "<h2>Recordings</h2>", '<p class="muted">Click a column to sort.</p>', _recording_table(items),
    ]
    parts += _listing("others", "Skipped: not recordings", others, lambda o: o.reason)
    parts += [
        '<script type="application/json" id="report-data">'
        + json.dumps([o.as_json() for o in items + others]).replace("</", "<\\/") + "</script>",
        f"<script>{SCRIPT}</script>", "</body></html>",
    ]
    return "\n".join(parts) + "\n"


def write_html(path: str | os.PathLike[str], outcomes: Sequence[Outcome], outdir: str) -> None:
    """``report.html``, written atomically."""
    text = render_html(outcomes, outdir)
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
