"""The station's CI report: a test run as Ant-style JUnit XML (what Jenkins and GitLab read).

``junit_xml(record)`` takes an OpenHTF test record (the dict OutputToJSON writes,
or a ``TestRecord``) and returns one ``<testsuites>`` holding one ``<testsuite>``
named after the plan, with one ``<testcase>`` per phase:

* a FAIL phase gets ``<failure type="measurement">`` naming each failing
  measurement with its value, unit and limit;
* an ERROR phase gets ``<error>`` with the exception's type and message; its text is
  the traceback for an unexpected exception (a bug) and just the sentence for an
  expected refusal (a drive refused at the preflight, an abort, a drive that stops
  answering: ``report.EXPECTED_EXCEPTIONS``);
* a SKIP phase gets ``<skipped/>``;
* a run that ended ERROR, ABORTED or TIMEOUT outside any phase (a plug that could
  not open the port, Ctrl-C between phases) gets one extra testcase, "test run",
  carrying that error, so CI never shows such a run as green.

The output validates against junit.xsd beside this module.
"""

import os
import re
import xml.etree.ElementTree as ET

from .report import (failed_measurements, format_value, measurement_text, operator_name, outcome_details_text,
                     phase_error_text, record_dict, seconds, utc_time, why_unset)

RUN_CASE = "test run"
SCHEMA = os.path.join(os.path.dirname(os.path.abspath(__file__)), "junit.xsd")
# Characters XML 1.0 cannot carry at all (ElementTree writes them as they are, and every
# parser then rejects the file): an exception text with a NUL or an ANSI colour code.
_NOT_XML = re.compile(r"[\x00-\x08\x0b\x0c\x0e-\x1f\ud800-\udfff\ufffe\uffff]")


def _properties(record):
    meta = record.get("metadata") or {}
    props = [("dut_id", record.get("dut_id")), ("plan_version", meta.get("test_version")),
             ("plan_hash", meta.get("plan_hash")), ("plan_file", meta.get("plan_file")),
             ("operator", operator_name(meta.get("operator"))), ("station", record.get("station_id")),
             ("outcome", record.get("outcome")), ("outcome_details", outcome_details_text(record)),
             ("verdict_reason", meta.get("verdict_reason"))]
    drive = meta.get("drive")
    if isinstance(drive, dict):
        props += [("drive_" + str(k), format_value(v)) for k, v in drive.items()]
    elif drive is not None:
        props.append(("drive", drive))
    return [(k, str(v)) for k, v in props if v not in (None, "")]


def _phase_error(record, phase, is_last):
    """(type, message, text) for an ERROR phase: the text is the traceback only for an unexpected
    exception; an expected refusal (report.EXPECTED_EXCEPTIONS) has its sentence."""
    err = phase_error_text(record, phase)
    if err:
        return err
    # Killed or stopped phases record no exception; the run's outcome details say why.
    details = outcome_details_text(record) if is_last else ""
    result = (phase.get("result") or {}).get("phase_result") or ""
    message = details or "phase ended in ERROR" + (" (%s)" % result if result else "")
    return str(result or record.get("outcome") or "ERROR"), message, message


def junit_xml(record):
    """The run as JUnit XML text (UTF-8, with an XML declaration)."""
    record = record_dict(record)
    meta = record.get("metadata") or {}
    plan = str(meta.get("test_name") or "openhtf_test")
    phases = record.get("phases") or []
    counts = {"tests": 0, "failures": 0, "errors": 0, "skipped": 0}

    suite = ET.Element("testsuite", name=plan)
    props = _properties(record)
    if props:
        el = ET.SubElement(suite, "properties")
        for name, value in props:
            ET.SubElement(el, "property", name=name, value=value)

    for i, phase in enumerate(phases):
        case = ET.SubElement(suite, "testcase", name=str(phase.get("name")), classname=plan,
                             time="%.3f" % seconds(phase.get("start_time_millis"), phase.get("end_time_millis")))
        counts["tests"] += 1
        outcome = phase.get("outcome")
        if outcome == "FAIL":
            counts["failures"] += 1
            failed = [measurement_text(m, why_unset(phase)) for m in failed_measurements(phase)]
            if failed:
                el = ET.SubElement(case, "failure", message="; ".join(failed), type="measurement")
                el.text = "\n".join(failed)
            else:  # the phase itself returned FAIL_AND_CONTINUE
                result = (phase.get("result") or {}).get("phase_result")
                el = ET.SubElement(case, "failure", message="phase failed (%s)" % result, type="phase")
        elif outcome == "ERROR":
            counts["errors"] += 1
            etype, message, text = _phase_error(record, phase, i == len(phases) - 1)
            ET.SubElement(case, "error", message=message, type=etype).text = text
        elif outcome == "SKIP":
            counts["skipped"] += 1
            ET.SubElement(case, "skipped", message="phase skipped")
        lines = [measurement_text(m) + " " + m.get("outcome", "") for m in (phase.get("measurements") or {}).values()]
        if lines:
            ET.SubElement(case, "system-out").text = "\n".join(lines)

    if record.get("outcome") in ("ERROR", "ABORTED", "TIMEOUT") and not counts["errors"]:
        case = ET.SubElement(suite, "testcase", name=RUN_CASE, classname=plan, time="0.000")
        details = record.get("outcome_details") or [{}]
        ET.SubElement(case, "error", message=outcome_details_text(record) or "run ended %s" % record["outcome"],
                      type=str(details[0].get("code") or record["outcome"])).text = outcome_details_text(record)
        counts["tests"] += 1
        counts["errors"] += 1

    total = "%.3f" % seconds(record.get("start_time_millis"), record.get("end_time_millis"))
    for key, value in counts.items():
        suite.set(key, str(value))
    suite.set("time", total)
    suite.set("timestamp", utc_time(record.get("start_time_millis"), sep="T") or utc_time(0, sep="T"))
    suite.set("hostname", str(record.get("station_id") or "unknown"))
    root = ET.Element("testsuites", name=plan, time=total, **{k: str(v) for k, v in counts.items()})
    root.append(suite)
    ET.indent(root)
    text = _NOT_XML.sub("\ufffd", ET.tostring(root, encoding="unicode"))
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + text + "\n"
