"""A stand-in for what cannot exist on this machine — a camera with a shutter and a settings
tree — around what can: libgphoto2's real "Directory Browse" driver on a folder (python-gphoto2's
wheel bundles it), which lists, downloads and deletes files as from a camera's card but has no
configuration and cannot capture.

`RecordedCamera` offers the methods of `gphoto2.Camera` that `Gphoto2Camera` calls:
* get_config / set_config: a widget tree parsed from a recorded `gphoto2 --list-all-config`
  text (tests/instruments/); set_config refuses a RADIO value the camera does not offer, with
  the GPhoto2Error the real library raises (GP_ERROR_BAD_PARAMETERS), and keeps a log;
* capture / wait_for_event: the "shutter" writes the frame file(s) into the folder the
  Directory Browse driver serves (NEF, and a JPEG too when the quality says NEF+...), returns
  the first path and announces the second as GP_EVENT_FILE_ADDED, as Nikon bodies do; a bulb
  exposure is the Bulb toggle pressed then released, timed on the test's clock;
* file_get / file_delete / get_abilities / exit: the real Directory Browse camera.
(python-gphoto2 cannot create CameraWidget or CameraFilePath objects, hence these classes.)
"""

from __future__ import annotations

from collections import deque
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import gphoto2 as gp

__all__ = ["RecordedWidget", "parse_config_text", "RecordedCamera"]

_TYPES = {
    "WINDOW": gp.GP_WIDGET_WINDOW, "SECTION": gp.GP_WIDGET_SECTION, "TEXT": gp.GP_WIDGET_TEXT,
    "RANGE": gp.GP_WIDGET_RANGE, "TOGGLE": gp.GP_WIDGET_TOGGLE, "RADIO": gp.GP_WIDGET_RADIO,
    "MENU": gp.GP_WIDGET_MENU, "BUTTON": gp.GP_WIDGET_BUTTON, "DATE": gp.GP_WIDGET_DATE,
}  # fmt: skip


class RecordedWidget:
    """The CameraWidget methods the driver uses, over recorded values."""

    def __init__(self, name: str, kind: int, value: Any = None, choices: list[str] | None = None):
        self.name, self.kind, self.value = name, kind, value
        self.choices = choices or []
        self.children: list[RecordedWidget] = []
        self.readonly = False

    def get_name(self) -> str:
        return self.name

    def get_type(self) -> int:
        return self.kind

    def get_value(self) -> Any:
        return self.value

    def set_value(self, value: Any) -> None:
        if self.readonly:
            raise gp.GPhoto2Error(gp.GP_ERROR_NOT_SUPPORTED)
        self.value = value

    def count_choices(self) -> int:
        return len(self.choices)

    def get_choice(self, i: int) -> str:
        return self.choices[i]

    def get_child_by_name(self, name: str) -> RecordedWidget:
        for child in self.walk():
            if child.name == name:
                return child
        raise gp.GPhoto2Error(gp.GP_ERROR_BAD_PARAMETERS)

    def walk(self):
        for child in self.children:
            yield child
            yield from child.walk()


def parse_config_text(text: str) -> RecordedWidget:
    """`gphoto2 --list-all-config` output → a tree (flat under the root: names are unique)."""
    root = RecordedWidget("main", gp.GP_WIDGET_WINDOW)
    entry: dict[str, Any] = {}
    for line in text.splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        if line.startswith("/"):
            entry = {"name": line.rsplit("/", 1)[-1], "choices": []}
        elif line == "END":
            kind = _TYPES[entry["type"]]
            value = entry.get("current")
            if kind == gp.GP_WIDGET_TOGGLE:
                value = int(value)
            w = RecordedWidget(entry["name"], kind, value, entry["choices"])
            w.readonly = entry.get("readonly") == "1"
            root.children.append(w)
        else:
            key, _, value = line.partition(": ")
            if key == "Choice":
                entry["choices"].append(value.split(" ", 1)[1])
            else:
                entry[key.lower()] = value
    return root


class RecordedCamera:
    """See the module docstring. `folder` is the directory the real `card` camera serves."""

    def __init__(self, card: Any, folder: Path, config_text: str, clock: Any) -> None:
        self.card, self.folder, self.clock = card, Path(folder), clock
        self.tree = parse_config_text(config_text)
        self.log: list[tuple[str, Any]] = []  # (widget, value) the camera accepted
        self.events: deque[tuple[int, Any]] = deque()
        self.bulb_s: list[float] = []  # measured press → release times
        self._shot = 0
        self._pressed_at: float | None = None
        self._last: dict[str, Any] = {w.name: w.value for w in self.tree.walk()}

    # -- settings -------------------------------------------------------------------------
    def get_config(self) -> RecordedWidget:
        return self.tree

    def set_config(self, tree: RecordedWidget) -> None:
        for w in tree.walk():
            if w.value == self._last[w.name]:
                continue
            if w.kind in (gp.GP_WIDGET_RADIO, gp.GP_WIDGET_MENU) and w.value not in w.choices:
                w.value = self._last[w.name]
                raise gp.GPhoto2Error(gp.GP_ERROR_BAD_PARAMETERS)
            self.log.append((w.name, w.value))
            self._last[w.name] = w.value
            if w.name == "bulb":
                self._bulb(int(w.value))

    def _bulb(self, pressed: int) -> None:
        if pressed:
            self._pressed_at = self.clock.now()
            return
        if self._pressed_at is None:
            return
        self.bulb_s.append(self.clock.now() - self._pressed_at)
        self._pressed_at = None
        for path in self._expose():
            self.events.append((gp.GP_EVENT_FILE_ADDED, path))

    # -- the shutter ----------------------------------------------------------------------
    def _expose(self) -> list[SimpleNamespace]:
        """Write this shot's file(s) on the 'card'; their camera paths, the RAW first."""
        import numpy as np

        from acquisition.frame_files import encode_dng

        self._shot += 1
        card_dir = self.folder / "DCIM" / "100D750"
        card_dir.mkdir(parents=True, exist_ok=True)
        stem = f"DSC_{self._shot:04d}"
        mosaic = np.full((32, 32), 100 + self._shot, dtype=np.uint16)  # a real (tiny) raw file
        (card_dir / f"{stem}.NEF").write_bytes(encode_dng(mosaic, {"shot": self._shot}))
        paths = [SimpleNamespace(folder="/DCIM/100D750", name=f"{stem}.NEF")]
        if str(self.tree.get_child_by_name("imagequality").value).startswith("NEF+"):
            (card_dir / f"{stem}.JPG").write_bytes(b"\xff\xd8 a JPEG the driver must not keep")
            paths.append(SimpleNamespace(folder="/DCIM/100D750", name=f"{stem}.JPG"))
        return paths

    def capture(self, kind: int) -> SimpleNamespace:
        assert kind == gp.GP_CAPTURE_IMAGE
        first, *more = self._expose()
        self.events.extend((gp.GP_EVENT_FILE_ADDED, p) for p in more)
        return first

    def wait_for_event(self, timeout_ms: int) -> tuple[int, Any]:
        if self.events:
            return self.events.popleft()
        return gp.GP_EVENT_TIMEOUT, None

    # -- the card: the real Directory Browse driver ---------------------------------------
    def file_get(self, folder: str, name: str, kind: int) -> Any:
        return self.card.file_get(folder, name, kind)

    def file_delete(self, folder: str, name: str) -> None:
        self.card.file_delete(folder, name)

    def get_abilities(self) -> Any:
        return self.card.get_abilities()

    def exit(self) -> None:
        self.card.exit()
