"""JUnit XML of a regression run: one ``<testcase>`` per check (standard library only).

The layout is the one CI servers read (Jenkins, GitLab, GitHub actions):
``<testsuites><testsuite name tests failures errors skipped time timestamp>
<properties/><testcase classname name time><failure message type>…``.
A check that is ``worse`` or ``changed`` is a ``<failure>``; ``better`` and
``ok`` pass (``better`` with a ``<system-out>`` note).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET

from .checks import Check, table


def _message(c: Check) -> str:
    def pct(v):
        return f"{100 * v:+.2f}%" if c.unit == "%" else f"{v:+.4g}"

    parts = [c.status]
    if c.change is not None:
        parts.append(f"change {pct(c.change)}")
    if c.tolerance is not None:
        parts.append(f"tolerance ±{pct(c.tolerance).lstrip('+')}")
    if c.z is not None:
        parts.append(f"z = {c.z:+.2f}")
    if c.baseline is not None or c.candidate is not None:
        parts.append(f"baseline {c.baseline!r}, candidate {c.candidate!r}")
    if c.detail:
        parts.append(c.detail)
    return "; ".join(parts)


def document(checks: list[Check], suite: str, properties: dict | None = None, seconds: float = 0.0,
             timestamp: str | None = None) -> ET.ElementTree:
    """The JUnit XML tree of ``checks`` (one test suite)."""
    failures = sum(c.failed for c in checks)
    root = ET.Element("testsuites", name="lfsim regress", tests=str(len(checks)), failures=str(failures),
                      errors="0", time=f"{seconds:.3f}")
    ts = ET.SubElement(root, "testsuite", name=suite, tests=str(len(checks)), failures=str(failures),
                       errors="0", skipped="0", time=f"{seconds:.3f}")
    if timestamp:
        ts.set("timestamp", timestamp)
    if properties:
        props = ET.SubElement(ts, "properties")
        for k, v in properties.items():
            ET.SubElement(props, "property", name=str(k), value=str(v))
    for c in checks:
        tc = ET.SubElement(ts, "testcase", classname=f"lfsim.regress.{c.group}", name=c.name, time="0")
        if c.failed:
            f = ET.SubElement(tc, "failure", message=_message(c), type=c.status)
            f.text = table([c])
        elif c.status == "better":
            ET.SubElement(tc, "system-out").text = _message(c)
    out = ET.SubElement(ts, "system-out")
    out.text = table(checks, include_ok=False) if failures or any(c.status == "better" for c in checks) else \
        f"{len(checks)} checks ok"
    ET.indent(root)
    return ET.ElementTree(root)


def write(path, checks: list[Check], suite: str, properties: dict | None = None, seconds: float = 0.0,
          timestamp: str | None = None) -> None:
    """Write the JUnit XML of ``checks`` to ``path`` atomically (UTF-8, with an XML declaration)."""
    from ..fileio import atomic_path

    tree = document(checks, suite, properties, seconds, timestamp)
    with atomic_path(path) as tmp:
        tree.write(tmp, encoding="utf-8", xml_declaration=True)
