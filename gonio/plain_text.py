"""Data printed as text: strings from manifests, configs, paths and device replies are never
interpreted as rich markup (``[/dev/ttyUSB0]`` is a closing tag to rich, and crashed `runs
show`), and control characters are shown escaped, so a terminal escape sequence in an event
message is displayed, not executed (issue 22, item 5)."""

from __future__ import annotations

from typing import Any

from rich.text import Text

__all__ = ["plain", "printable"]

# C0 controls (tab kept), DEL and C1 controls: ESC starts terminal escape sequences, CR
# rewrites the line, BEL rings. Shown as \xNN.
_CONTROL = {c: f"\\x{c:02x}" for c in (*range(0x00, 0x09), *range(0x0A, 0x20), *range(0x7F, 0xA0))}


def printable(value: Any) -> str:
    """str(value) with control characters escaped."""
    return str(value).translate(_CONTROL)


def plain(value: Any) -> Text:
    """A rich Text of `value`: printed as it is, never parsed for markup."""
    return Text(printable(value))
