"""The campaign report of ``magcal batch``: ``report.csv`` and a self-contained ``report.html``.

One row per recording (:data:`COLUMNS`): sets, drops, time span, the TMI residual
``| |B| - F |`` (median and 95th percentile, T and in units of the calibration's noise),
the tensor noise and the calibration used. The HTML page adds, per vehicle, the trend of
those over the recordings' start times as inline SVG charts (no external file, script or
font), so a calibration drifting between missions shows at a glance: with Gaussian noise
of standard deviation ``s`` per axis a calibration that holds gives a median near
``0.67 s`` and a 95th percentile near ``1.96 s`` (dashed lines). Every number in the page's
tables carries its exact value in a ``data-value`` attribute. Files a walk met that are not
recordings are listed as skipped.
"""

from __future__ import annotations

import csv
import html
import io
import json
import math
import os
from collections.abc import Callable, Sequence
from datetime import datetime, timezone
from pathlib import Path

from magcal_ros.app.campaign import Outcome
from magcal_ros.core.stamps import format_seconds, ns_to_seconds
from magcal_ros.core.units import NT
from magcal_ros.io.atomic import atomic_path

COLUMNS: tuple[str, ...] = (
    "recording", "vehicle", "status", "start", "end", "start_utc", "duration_s", "sets", "drops",
    "intensity_T", "noise_T", "tmi_median_T", "tmi_p95_T", "tmi_median_noise", "tmi_p95_noise",
    "tensor_noise_T_per_m", "calibration", "input", "output", "seconds", "worker", "reason", "notes",
)
"""Columns of ``report.csv`` (times in decimal seconds, exact; fields in T, gradients in T/m)."""

GAUSSIAN_MEDIAN = 0.6745
"""Median of ``|x|`` for a standard normal ``x``: the TMI residual of a calibration that holds, in noise units."""
GAUSSIAN_P95 = 1.96
"""95th percentile of ``|x|`` for a standard normal ``x``."""


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
tr.failed td{background:#fdecec} tr.skipped td{color:#555}
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
)
TEXT_KEYS = {"recording", "vehicle", "status", "start", "calibration", "reason"}


def _nice_step(span: float, ticks: int = 5) -> float:
    raw = span / max(ticks, 1)
    mag = 10 ** math.floor(math.log10(raw)) if raw > 0 else 1.0
    return next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw)


def svg_chart(title: str, unit: str, series: dict[str, list[tuple[int, float, str]]],
              colours: dict[str, str], references: Sequence[tuple[float, str]] = ()) -> str:
    """A line chart (inline SVG): per vehicle, ``(start ns, value, label)`` points joined in time order."""
    w, h, left, right, top, bottom = 440, 250, 58, 12, 28, 42
    pts = [(t, v) for s in series.values() for t, v, _ in s if v is not None and math.isfinite(v)]
    out = [f'<svg class="chart" xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" viewBox="0 0 {w} {h}" '
           f'data-title="{html.escape(title)}">',
           f'<text x="{w / 2}" y="17" text-anchor="middle" font-size="13" font-weight="bold">{html.escape(title)}</text>']
    if not pts:
        out.append(f'<text x="{w / 2}" y="{h / 2}" text-anchor="middle" font-size="12" fill="#888">no data</text></svg>')
        return "\n".join(out)
    t0, t1 = min(p[0] for p in pts), max(p[0] for p in pts)
    if t1 == t0:
        t0, t1 = t0 - 3600 * 10**9, t1 + 3600 * 10**9
    vmax = max([p[1] for p in pts] + [r[0] for r in references]) * 1.1 or 1.0
    step = _nice_step(vmax)
    vmax = math.ceil(vmax / step) * step
    pw, ph = w - left - right, h - top - bottom

    def x(t: int) -> float:
        return left + pw * (t - t0) / (t1 - t0)

    def y(v: float) -> float:
        return top + ph * (1 - v / vmax)

    out.append(f'<rect x="{left}" y="{top}" width="{pw}" height="{ph}" fill="none" stroke="#bbb"/>')
    k = 0
    while k * step <= vmax + 1e-12 * vmax:
        v = k * step
        out.append(f'<line x1="{left}" x2="{left + pw}" y1="{y(v):.1f}" y2="{y(v):.1f}" stroke="#eee"/>'
                   f'<text x="{left - 4}" y="{y(v) + 4:.1f}" text-anchor="end" font-size="10">{v:g}</text>')
        k += 1
    for i in range(4):
        t = t0 + (t1 - t0) * i // 3
        anchor = ("start", "middle", "middle", "end")[i]
        out.append(f'<text x="{x(t):.1f}" y="{top + ph + 14}" text-anchor="{anchor}" font-size="10">'
                   f'{html.escape(_utc(t, seconds=False))}</text>')
    out.append(f'<text x="14" y="{top + ph / 2}" transform="rotate(-90 14 {top + ph / 2})" text-anchor="middle" '
               f'font-size="11">{html.escape(unit)}</text>')
    for value, label in references:
        out.append(f'<line x1="{left}" x2="{left + pw}" y1="{y(value):.1f}" y2="{y(value):.1f}" stroke="#999" '
                   f'stroke-dasharray="4 3"><title>{html.escape(label)}</title></line>')
    legend_x = left
    for vehicle, points in series.items():
        colour = colours[vehicle]
        good = sorted((t, v, lab) for t, v, lab in points if v is not None and math.isfinite(v))
        if not good:
            continue
        line = " ".join(f"{x(t):.1f},{y(v):.1f}" for t, v, _ in good)
        out.append(f'<polyline class="trend" data-vehicle="{html.escape(vehicle)}" points="{line}" fill="none" '
                   f'stroke="{colour}" stroke-width="1.5"/>')
        for t, v, lab in good:
            out.append(f'<circle cx="{x(t):.1f}" cy="{y(v):.1f}" r="3.5" fill="{colour}" data-recording="{html.escape(lab)}" '
                       f'data-value="{v!r}"><title>{html.escape(lab)}: {v:.3g} {html.escape(unit)}</title></circle>')
        out.append(f'<rect x="{legend_x}" y="{h - 12}" width="9" height="9" fill="{colour}"/>'
                   f'<text x="{legend_x + 12}" y="{h - 4}" font-size="10">{html.escape(vehicle or "(no vehicle)")}</text>')
        legend_x += 18 + 7 * len(vehicle or "(no vehicle)")
    out.append("</svg>")
    return "\n".join(out)


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
        refs = [(ref, "a calibration that holds (Gaussian noise)")] if relative else []
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
        rows.append(f'<tr class="{html.escape(o.status)}" data-name="{html.escape(o.name)}">' + "".join(cells) + "</tr>")
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
    when = (created or datetime.now(timezone.utc)).strftime("%Y-%m-%d %H:%M:%S UTC")
    more = (f" {len(others)} file{'s' if len(others) != 1 else ''} found that {'are' if len(others) != 1 else 'is'} "
            "not a recording: skipped." if others else "")
    return (f'<p class="summary" id="summary" data-recordings="{len(items)}" data-corrected="{corrected}" '
            f'data-skipped="{skipped}" data-failed="{failed}" data-others="{len(others)}">'
            f"{len(items)} recordings: {corrected} corrected, {skipped} skipped (done by an earlier run, unchanged), "
            f"{failed} failed.{more} Outputs in <code>{html.escape(outdir)}</code> (every output a run wrote there "
            f"and that is still as written); written {when} by <code>magcal batch</code>.</p>")


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
    parts += [
        "<h2>Per vehicle over time</h2>",
        '<p class="muted">Each point is a recording at its first set\'s time, joined per vehicle. TMI residual: '
        "<code>| |B| - F |</code> over every corrected vector, F the calibration's reference intensity, in units of "
        "the calibration's noise per axis; a calibration that holds stays near the dashed lines (0.67 for the "
        "median, 1.96 for the 95th percentile with Gaussian noise), one that drifts between missions climbs "
        "away from them. Tensor noise: the set-to-set noise of the six measured gradient components.</p>",
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
