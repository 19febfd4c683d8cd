"""The station's human report: one self-contained HTML file per test run.

``html_report(record)`` renders an OpenHTF test record (the dict that
``OutputToJSON(..., inline_attachments=True)`` writes, or a ``TestRecord``) as a
page that opens offline: inline CSS, inline SVG plots, no script, no external
URL. It shows the verdict, the run's identity (DUT, plan, operator, station,
drive, times), every phase with its measurements and limits, the position and
velocity plots of each move phase's "trace" attachment, the jig's bus counters
and the errors. Every string taken from the record is HTML-escaped.

The record helpers at the top (``record_dict``, ``attachment_json``,
``measurement_text``...) are shared with ``junit.py``.
"""

import base64
import datetime
import html
import json
import math

OUTCOME_COLOURS = {"PASS": "pass", "FAIL": "fail", "ERROR": "warn", "ABORTED": "warn", "TIMEOUT": "warn"}


# --- reading the record -------------------------------------------------------------------------

def record_dict(record):
    """The record as ``json.load()`` returns it for a file written by
    ``OutputToJSON(path, inline_attachments=True)``; a dict is returned as it is."""
    if isinstance(record, dict):
        return record
    from openhtf.output.callbacks import json_factory

    # The very functions OutputToJSON uses, then a JSON round trip: a report made now and
    # one regenerated later from the saved file are the same.
    encoded = json_factory.convert_test_record_to_json(record, inline_attachments=True)
    return json.loads("".join(json_factory.stream_json(encoded)))


def attachment_json(phase, name):
    """The decoded JSON of the phase's attachment ``name``, or None (absent, not inlined, not JSON)."""
    att = (phase.get("attachments") or {}).get(name)
    if not isinstance(att, dict) or "data" not in att:
        return None
    try:
        return json.loads(base64.standard_b64decode(att["data"]).decode("utf-8"))
    except (ValueError, UnicodeDecodeError):
        return None


def utc_time(millis, sep=" "):
    """ISO 8601 time in UTC of a ms-since-epoch stamp (UTC so every machine renders the same)."""
    if millis is None:
        return ""
    t = datetime.datetime.fromtimestamp(millis / 1000.0, datetime.timezone.utc)
    return t.isoformat(sep=sep, timespec="seconds")


def seconds(start_millis, end_millis):
    """Duration in seconds, 0 when a stamp is missing."""
    if start_millis is None or end_millis is None:
        return 0.0
    return max(0.0, (end_millis - start_millis) / 1000.0)


def duration_text(secs):
    if secs < 1:
        return "%d ms" % round(secs * 1000)
    if secs < 60:
        return "%.2f s" % secs
    return "%d min %02d s" % divmod(round(secs), 60)


def format_value(value):
    if isinstance(value, bool):
        return str(value)
    if isinstance(value, float):
        return "%.10g" % value
    if isinstance(value, (list, dict)):
        return json.dumps(value, separators=(",", ":"))
    return str(value)


def unit_text(meas):
    units = meas.get("units") or {}
    return units.get("suffix") or units.get("name") or ""


def limits_text(meas):
    """The validators' string forms, as OpenHTF recorded them."""
    return " and ".join(str(v) for v in meas.get("validators") or ())


def why_unset(phase):
    """{measurement: why it was not measured} the step attached ("why_unset"), or {}."""
    why = attachment_json(phase, "why_unset")
    return why if isinstance(why, dict) else {}


def measurement_text(meas, why=None):
    """One line for a measurement: 'name = 812 pulse, outside -10 <= x <= 10' when it failed."""
    name = meas.get("name", "?")
    if "measured_value" not in meas:
        return "%s was not measured%s" % (name, ": " + why[name] if why and name in why else "")
    value = format_value(meas["measured_value"])
    unit = unit_text(meas)
    text = "%s = %s%s" % (name, value, " " + unit if unit else "")
    limits = limits_text(meas)
    if meas.get("outcome") == "FAIL":
        return text + (", outside " + limits if limits else ", failed")
    return text + (" (%s)" % limits if limits else "")


def failed_measurements(phase):
    """The measurements that did not pass (a SKIPPED one, left out on purpose, is not among them)."""
    return [m for m in (phase.get("measurements") or {}).values() if m.get("outcome") not in ("PASS", "SKIPPED")]


def phase_exception(phase):
    """(type, message, traceback) of the exception that ended the phase, or None."""
    result = (phase.get("result") or {}).get("phase_result")
    if not isinstance(result, dict):
        return None
    exc_type = str(result.get("exc_type", "Exception"))
    if exc_type.startswith("<class '") and exc_type.endswith("'>"):
        exc_type = exc_type[8:-2]
    return exc_type, str(result.get("exc_val", "")), str(result.get("exc_tb", ""))


def operator_name(value):
    """Who ran the test, as reports, JUnit and the database show it: 'unknown' when the record has
    nobody (no --operator and $USER unset: a service, a container)."""
    text = "" if value is None else str(value).strip()
    return text or "unknown"


# Exceptions that end a run on purpose, each with a sentence that says all there is to say: a drive
# refused at the preflight or a prompt nobody can answer (PreflightError), an abort (RunAborted,
# OpenHTF's ThreadTerminationError, Ctrl-C), the bus library's errors (motorjig.errors: a drive
# that stops answering, a refused command), a bad plan or database. Reports give their sentence;
# a traceback only for anything else (a bug).
EXPECTED_EXCEPTIONS = frozenset((
    "motorjig.station.runner.PreflightError", "motorjig.station.phases.RunAborted",
    "openhtf.util.threads.ThreadTerminationError", "KeyboardInterrupt", "motorjig.tomlsource.SourceError",
    "motorjig.station.store.StoreError", "motorjig.station.sampling.UntrustedMeasurement"))
ABORT_EXCEPTIONS = frozenset(("motorjig.station.phases.RunAborted", "openhtf.util.threads.ThreadTerminationError",
                              "KeyboardInterrupt"))


def expected_exception(exc_type):
    """True for an exception type (its recorded name) that ends a run on purpose (EXPECTED_EXCEPTIONS)."""
    return exc_type in EXPECTED_EXCEPTIONS or exc_type.startswith("motorjig.errors.")


def phase_error_text(record, phase):
    """(type, sentence, body) of the exception that ended a phase, or None: the body is the sentence
    for an expected refusal and the traceback for anything else."""
    exc = phase_exception(phase)
    if not exc:
        return None
    exc_type, message, tb = exc
    if expected_exception(exc_type):
        if not message and exc_type in ABORT_EXCEPTIONS:
            message = outcome_details_text(record) or "the run was aborted"
        sentence = message or exc_type.rsplit(".", 1)[-1]
        return exc_type, sentence, sentence
    sentence = "%s: %s" % (exc_type, message) if message else exc_type
    return exc_type, sentence, tb or message


def outcome_details_text(record):
    return "; ".join("%s: %s" % (d.get("code"), d.get("description")) if d.get("description") else str(d.get("code"))
                     for d in record.get("outcome_details") or ())


# --- SVG plots ----------------------------------------------------------------------------------

def _axis(lo, hi, pad, count=6):
    """(axis_lo, axis_hi, ticks): the data range widened by pad (a fraction), ticks on a 1-2-5 step inside it."""
    if not hi > lo:
        lo, hi = lo - 1, hi + 1
    lo, hi = lo - pad * (hi - lo), hi + pad * (hi - lo)
    raw = (hi - lo) / count
    mag = 10 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 5, 10) if m * mag >= raw * 0.999)
    first, last = math.ceil(lo / step - 1e-9), math.floor(hi / step + 1e-9)
    return lo, hi, [i * step for i in range(first, last + 1)]


def _num(v):
    return "%.10g" % (round(v, 9) + 0.0)


def svg_plot(title, x, series, x_label, y_label, hline=None, width=560, height=290):
    """An SVG line chart. series: [(label, ys, css_class)]; hline: (label, y) drawn dashed."""
    left, right, top, bottom = 70, 14, 34, 46
    pw, ph = width - left - right, height - top - bottom
    pts = [(a, b) for _, ys, _ in series for a, b in zip(x, ys) if a is not None and b is not None]
    ys_all = [b for _, b in pts] + ([hline[1]] if hline else [])
    if not pts:
        return '<p class="muted">%s: no data</p>' % html.escape(title)
    x0, x1, xt = _axis(min(a for a, _ in pts), max(a for a, _ in pts), 0.0, 8)
    y0, y1, yt = _axis(min(ys_all), max(ys_all), 0.06)

    def sx(v):
        return left + (v - x0) / (x1 - x0) * pw

    def sy(v):
        return top + ph - (v - y0) / (y1 - y0) * ph

    out = ['<svg class="plot" viewBox="0 0 %d %d" role="img" aria-label="%s">'
           % (width, height, html.escape(title)),
           '<text class="title" x="%d" y="20">%s</text>' % (left, html.escape(title))]
    for v in yt:
        out.append('<line class="grid" x1="%d" x2="%d" y1="%.1f" y2="%.1f"/>' % (left, left + pw, sy(v), sy(v)))
        out.append('<text class="tick" x="%d" y="%.1f" text-anchor="end">%s</text>' % (left - 6, sy(v) + 4, _num(v)))
    for v in xt:
        out.append('<line class="grid" x1="%.1f" x2="%.1f" y1="%d" y2="%d"/>' % (sx(v), sx(v), top, top + ph))
        out.append('<text class="tick" x="%.1f" y="%d" text-anchor="middle">%s</text>' % (sx(v), top + ph + 16, _num(v)))
    out.append('<rect class="frame" x="%d" y="%d" width="%d" height="%d"/>' % (left, top, pw, ph))
    out.append('<text class="label" x="%.1f" y="%d" text-anchor="middle">%s</text>'
               % (left + pw / 2, height - 8, html.escape(x_label)))
    out.append('<text class="label" transform="translate(16 %.1f) rotate(-90)" text-anchor="middle">%s</text>'
               % (top + ph / 2, html.escape(y_label)))
    legend = []
    if hline:
        ty = sy(hline[1])
        out.append('<line class="target" x1="%d" x2="%d" y1="%.1f" y2="%.1f"/>' % (left, left + pw, ty, ty))
        legend.append((hline[0], "target"))
    for label, ys, css in series:
        points = " ".join("%.1f,%.1f" % (sx(a), sy(b)) for a, b in zip(x, ys) if a is not None and b is not None)
        out.append('<polyline class="series %s" data-points="%d" points="%s"/>' % (css, points.count(","), points))
        legend.append((label, css))
    lx = left + pw
    for label, css in reversed(legend):  # right-aligned legend above the plot
        lx -= 16 + 7 * len(label)
        out.append('<line class="%s" x1="%d" x2="%d" y1="16" y2="16"/><text class="legend" x="%d" y="20">%s</text>'
                   % (css if css == "target" else "series " + css, lx, lx + 18, lx + 22, html.escape(label)))
        lx -= 30
    out.append("</svg>")
    return "\n".join(out)


def _is_number(v):
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def trace_plots(trace):
    """The position and velocity plots of a move phase's trace attachment."""
    cols = list(trace.get("columns") or [])
    units = trace.get("units") or {}
    rows = [r for r in trace.get("rows") or () if isinstance(r, (list, tuple))]

    def column(name):
        if name not in cols:
            return None
        i = cols.index(name)
        return [r[i] if i < len(r) and _is_number(r[i]) else None for r in rows]

    t = column("t") or []
    t_label = "time (%s)" % units.get("t", "s")
    pos = [(name.capitalize(), column(name), name) for name in ("command", "actual") if column(name)]
    pos_unit = units.get("actual") or units.get("command") or ""
    target = trace.get("target")
    hline = ("Target", target) if _is_number(target) else None
    plots = [svg_plot("Position", t, pos, t_label, "position (%s)" % pos_unit, hline)]
    vel = column("velocity")
    if vel:
        plots.append(svg_plot("Velocity", t, [("Velocity", vel, "velocity")], t_label,
                              "velocity (%s)" % units.get("velocity", "")))
    return plots


# --- the page -----------------------------------------------------------------------------------

CSS = """
*{box-sizing:border-box}
body{margin:0;color:#202124;background:#f4f5f7;
 font:14px/1.45 system-ui,-apple-system,"Segoe UI",Roboto,"DejaVu Sans",Arial,sans-serif}
main{max-width:1180px;margin:0 auto;padding:0 24px 32px}
.banner{display:flex;align-items:center;gap:28px;padding:18px 28px;color:#fff}
.banner.pass{background:#137333}.banner.fail{background:#c5221f}.banner.warn{background:#f9ab00;color:#202124}
.verdict{font-size:52px;font-weight:800;letter-spacing:2px;line-height:1}
.headline{font-size:18px}.headline .plan{font-size:22px;font-weight:600}
.reason{margin-top:4px;font-size:15px;opacity:.95}
section{background:#fff;border:1px solid #dadce0;border-radius:6px;margin-top:18px;padding:14px 18px}
h2{font-size:16px;margin:0 0 10px}h3{font-size:14px;margin:4px 0 6px}
dl.info{display:grid;grid-template-columns:repeat(3,auto 1fr);gap:4px 14px;margin:0}
dl.info dt{color:#5f6368}dl.info dd{margin:0;font-weight:500;overflow-wrap:anywhere}
table{border-collapse:collapse;width:100%}
th,td{text-align:left;padding:4px 8px;border-bottom:1px solid #e8eaed;vertical-align:top}
thead th{background:#f1f3f4;font-weight:600;color:#3c4043}
tr.phase td{background:#f8f9fa;font-weight:600;border-top:2px solid #dadce0}
tr.meas td:first-child{padding-left:26px}
tr.meas.fail td{background:#fce8e6;color:#a50e0e;font-weight:600}
td.num{text-align:right;font-variant-numeric:tabular-nums;font-family:ui-monospace,"DejaVu Sans Mono",monospace}
.badge{display:inline-block;min-width:54px;text-align:center;padding:1px 8px;border-radius:10px;
 font-size:12px;font-weight:700;color:#fff}
.badge.PASS{background:#137333}.badge.FAIL{background:#c5221f}
.badge.ERROR,.badge.ABORTED,.badge.TIMEOUT{background:#f9ab00;color:#202124}
.badge.SKIP,.badge.SKIPPED,.badge.UNSET{background:#9aa0a6}
.muted{color:#5f6368;font-weight:400}
.plots{display:grid;grid-template-columns:1fr 1fr;gap:10px}
.trace{border-top:1px solid #e8eaed;padding-top:8px;margin-top:8px}.trace:first-of-type{border-top:0;margin-top:0}
svg.plot{width:100%;height:auto;background:#fff}
svg .title{font-size:14px;font-weight:600;fill:#202124}svg .tick{font-size:11px;fill:#5f6368}
svg .label{font-size:12px;fill:#3c4043}svg .legend{font-size:12px;fill:#3c4043}
svg .grid{stroke:#e8eaed;stroke-width:1}svg .frame{fill:none;stroke:#9aa0a6;stroke-width:1}
svg .series{fill:none;stroke-linejoin:round;stroke-linecap:round}
svg .command{stroke:#8ab4f8;stroke-width:4}svg .actual{stroke:#d93025;stroke-width:1.6}
svg .velocity{stroke:#188038;stroke-width:1.8}svg .target{stroke:#3c4043;stroke-width:1.3;stroke-dasharray:6 4}
pre{white-space:pre-wrap;word-break:break-word;background:#fff8e1;border:1px solid #f9ab00;border-radius:4px;
 padding:8px 10px;margin:6px 0;font:12px/1.4 ui-monospace,"DejaVu Sans Mono",monospace}
table.counters{width:auto;min-width:360px}
footer{color:#5f6368;font-size:12px;margin-top:14px}
"""


def _e(value):
    return html.escape("" if value is None else str(value))


def _badge(outcome):
    return '<span class="badge %s">%s</span>' % (_e(outcome), _e(outcome))


def _info(record):
    meta = record.get("metadata") or {}
    plan_hash = str(meta.get("plan_hash") or "")
    drive = meta.get("drive")
    if isinstance(drive, dict):
        drive_text = ", ".join(([str(drive["name"])] if drive.get("name") else []) +
                               ["%s %s" % (k.replace("_", " "), v) for k, v in drive.items() if k != "name"])
    else:
        drive_text = "" if drive is None else str(drive)
    start, end = record.get("start_time_millis"), record.get("end_time_millis")
    items = [
        ("DUT serial", _e(record.get("dut_id")), "dut"),
        ("Plan", "%s <span class=\"muted\">v%s</span>" % (_e(meta.get("test_name")), _e(meta.get("test_version"))), "plan"),
        ("Plan hash", '<span title="%s">%s%s</span>'
         % (_e(plan_hash), _e(plan_hash[:12]), "&hellip;" if len(plan_hash) > 12 else ""), "hash"),
        ("Operator", _e(operator_name(meta.get("operator"))), "operator"),
        ("Station", _e(record.get("station_id")), "station"),
        ("Plan file", _e(meta.get("plan_file")), "plan-file"),
        ("Start", _e(utc_time(start)) + " UTC" if start else "", "start"),
        ("End", _e(utc_time(end)) + " UTC" if end else "", "end"),
        ("Duration", duration_text(seconds(start, end)), "duration"),
        ("Drive", _e(drive_text), "drive"),
    ]
    return "<dl class=\"info\">%s</dl>" % "".join(
        '<dt>%s</dt><dd data-testid="info-%s">%s</dd>' % (k, testid, v) for k, v, testid in items)


def _phase_table(phases):
    rows = []
    for p in phases:
        meas = list((p.get("measurements") or {}).values())
        err = phase_error_text({}, p)
        note = err[1] if err else ("" if meas else "no measurements")
        rows.append('<tr class="phase" data-phase="%s"><td>%s</td><td colspan="3" class="muted">%s</td>'
                    '<td class="num">%s</td><td>%s</td></tr>'
                    % (_e(p.get("name")), _e(p.get("name")), _e(note),
                       duration_text(seconds(p.get("start_time_millis"), p.get("end_time_millis"))),
                       _badge(p.get("outcome"))))
        why = why_unset(p)
        for m in meas:
            outcome = m.get("outcome", "UNSET")
            value = (format_value(m["measured_value"]) if "measured_value" in m
                     else "not measured: " + why[m.get("name")] if m.get("name") in why else "not measured")
            short = value if len(value) <= 60 else value[:57] + "..."  # a dimensioned measurement's whole table
            align = "num" if _is_number(m.get("measured_value")) else "text"
            rows.append('<tr class="meas%s" data-measurement="%s" data-outcome="%s"><td>%s</td>'
                        '<td class="%s" title="%s">%s</td><td>%s</td><td>%s</td><td></td><td>%s</td></tr>'
                        % (" fail" if outcome not in ("PASS", "SKIPPED") else "", _e(m.get("name")), _e(outcome), _e(m.get("name")),
                           align, _e(value), _e(short), _e(unit_text(m)), _e(limits_text(m)), _badge(outcome)))
    return ('<table class="phases" data-testid="phases"><thead><tr><th>Phase / measurement</th><th>Value</th>'
            '<th>Unit</th><th>Limits</th><th>Time</th><th>Result</th></tr></thead><tbody>%s</tbody></table>'
            % "\n".join(rows))


def _errors(record):
    parts = ["<p><b>%s</b>: %s</p>" % (_e(d.get("code")), _e(d.get("description")))
             for d in record.get("outcome_details") or ()]
    for p in record.get("phases") or ():
        err = phase_error_text(record, p)
        if err:
            parts.append("<h3>Phase %s: %s</h3><pre>%s</pre>" % (_e(p.get("name")), _e(err[0]), _e(err[2])))
    return ('<section data-testid="errors"><h2>Errors</h2>%s</section>' % "\n".join(parts)) if parts else ""


def _traces(phases):
    out = []
    for p in phases:
        trace = attachment_json(p, "trace")
        if not isinstance(trace, dict):
            continue
        target = trace.get("target")
        out.append('<div class="trace" data-testid="trace" data-phase="%s"><h3>%s %s%s</h3><div class="plots">%s</div></div>'
                   % (_e(p.get("name")), _e(p.get("name")), _badge(p.get("outcome")),
                      ' <span class="muted">target %s</span>' % _e(target) if target is not None else "",
                      "".join("<div>%s</div>" % svg for svg in trace_plots(trace))))
    return ('<section data-testid="traces"><h2>Move traces</h2>%s</section>' % "\n".join(out)) if out else ""


def _counters(phases):
    out = []
    for p in phases:
        counters = attachment_json(p, "bus_counters")
        if not isinstance(counters, dict):
            continue
        rows = "".join('<tr><td>%s</td><td class="num">%s</td></tr>' % (_e(k), _e(format_value(v)))
                       for k, v in counters.items())
        out.append('<h3>%s</h3><table class="counters" data-testid="bus-counters"><thead><tr><th>Counter</th>'
                   '<th>Value</th></tr></thead><tbody>%s</tbody></table>' % (_e(p.get("name")), rows))
    return ("<section><h2>Bus counters (jig)</h2>%s</section>" % "\n".join(out)) if out else ""


def html_report(record):
    """The run's report as one self-contained HTML page (str)."""
    record = record_dict(record)
    meta = record.get("metadata") or {}
    phases = record.get("phases") or []
    outcome = str(record.get("outcome") or "UNKNOWN")
    verdict = outcome + (" (MARGINAL)" if record.get("marginal") else "")
    reason = meta.get("verdict_reason") or outcome_details_text(record)
    if not reason and outcome == "FAIL":
        reason = "; ".join(measurement_text(m, why_unset(p)) for p in phases for m in failed_measurements(p))
    title = "%s %s %s" % (verdict, meta.get("test_name") or "", record.get("dut_id") or "")
    tally = [(sum(p.get("outcome") == o for p in phases), word) for o, word in
             (("PASS", "passed"), ("FAIL", "failed"), ("ERROR", "error"), ("SKIP", "skipped"))]
    tally = "%d phases: %s" % (len(phases), ", ".join("%d %s" % t for t in tally if t[0]) or "none ran")
    return """<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><meta name="viewport" content="width=device-width,initial-scale=1">
<title>%s</title><style>%s</style></head>
<body>
<header class="banner %s" data-testid="verdict" data-outcome="%s"><div class="verdict" data-testid="verdict-text">%s</div>
<div class="headline"><div class="plan">%s <span>v%s</span></div><div>DUT %s &middot; %s</div>%s</div></header>
<main>
<section><h2>Run</h2>%s</section>
%s
<section><h2>Phases and measurements</h2>%s</section>
%s
%s
<footer>MotorJig station report, generated from the OpenHTF test record. Times are UTC.</footer>
</main></body></html>
""" % (_e(title.strip()), CSS, OUTCOME_COLOURS.get(outcome, "warn"), _e(outcome), _e(verdict),
       _e(meta.get("test_name")), _e(meta.get("test_version")), _e(record.get("dut_id")), _e(tally),
       '<div class="reason" data-testid="verdict-reason">%s</div>' % _e(reason) if reason else "",
       _info(record), _errors(record), _phase_table(phases), _counters(phases), _traces(phases))
