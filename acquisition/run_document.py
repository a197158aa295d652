"""`run.toml`, typed: what a run froze about itself, read and written in one place.

Sections (docs/design.md §4): `schema_version`; `[gonio]` version and start time; `[rig]` and
`[plan]` as given; what calibration uses — `[camera]` (the rig file's description with the
intrinsics resolved, acquisition.description), `[sample]`, `[arm_offsets]` (the geometric
calibration file's content, when the rig names one); `[camera_device]` (what the camera reported
about itself, for the record); and `[scene]` for a simulated rig (the emulated world, to rebuild the
emulators on resume — calibration never reads it).
"""

from __future__ import annotations

import datetime as _dt
from pathlib import Path
from typing import Any

import tomli_w
from pydantic import BaseModel, ConfigDict, ValidationError

from acquisition.config import PlanConfig, RigConfig
from acquisition.store import SCHEMA_VERSION, RunStore, RunStoreError
from plumbing.config import format_validation_error

__all__ = ["DEVICE_SECTIONS", "RunDocument", "device_difference"]

# The parts of a rig that name hardware or run something: a resumed run must match the rig
# file the user gives in these, so a run directory never chooses devices or commands.
DEVICE_SECTIONS = ("clock", "bus", "light", "camera", "axes")


def _clean(d: Any) -> Any:
    """TOML has no null: drop None values recursively."""
    if isinstance(d, dict):
        return {k: _clean(v) for k, v in d.items() if v is not None}
    if isinstance(d, list | tuple):
        return [_clean(v) for v in d]
    return d


class RunDocument(BaseModel):
    """The typed run.toml (see module doc)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    schema_version: int = SCHEMA_VERSION
    gonio: dict[str, str]
    rig: RigConfig
    plan: PlanConfig
    camera: dict[str, Any]
    camera_device: dict[str, Any] = {}
    sample: dict[str, Any]
    arm_offsets: dict[str, Any] | None = None
    scene: dict[str, Any] | None = None

    @classmethod
    def new(
        cls,
        rig: RigConfig,
        plan: PlanConfig,
        *,
        version: str,
        device: dict[str, Any],
        scene: dict[str, Any] | None = None,
    ) -> RunDocument:
        """The document a new run freezes: the rig file's description resolved now."""
        from acquisition.description import (
            arm_offsets_description,
            camera_description,
            sample_description,
        )

        started = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
        return cls(
            gonio={"version": version, "started_at": started},
            rig=rig,
            plan=plan,
            camera=camera_description(rig),
            camera_device=device,
            sample=sample_description(rig),
            arm_offsets=arm_offsets_description(rig),
            scene=scene,
        )

    def toml(self) -> str:
        doc = self.model_dump(mode="json")
        # Top-level keys must precede the first table: the version first, so a reader can
        # refuse a newer run before interpreting anything else.
        return tomli_w.dumps(_clean({"schema_version": doc.pop("schema_version"), **doc}))

    @classmethod
    def of(cls, store: RunStore) -> RunDocument:
        """The run's document; one-line errors for an older, newer or damaged run.toml."""
        raw = store.run_config()  # refuses a newer schema, damaged TOML
        path = Path(store.root) / "run.toml"
        version = raw.get("schema_version", 1)
        if version < SCHEMA_VERSION:
            raise RunStoreError(
                f"{path}: schema version {version} (an older gonio, before rig files described "
                "the camera and sample); reduce it with that version, or re-acquire"
            )
        try:
            return cls.model_validate(raw)
        except ValidationError as err:
            raise RunStoreError(format_validation_error(path, err, cls)) from None


def _first_difference(a: Any, b: Any, path: str) -> tuple[str, Any, Any] | None:
    if isinstance(a, dict) and isinstance(b, dict):
        for key in sorted(set(a) | set(b), key=str):
            found = _first_difference(a.get(key), b.get(key), f"{path}.{key}")
            if found:
                return found
        return None
    if isinstance(a, list | tuple) and isinstance(b, list | tuple) and len(a) == len(b):
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            found = _first_difference(x, y, f"{path}[{i}]")
            if found:
                return found
        return None
    return None if a == b else (path, a, b)


def device_difference(frozen: RigConfig, trusted: RigConfig) -> tuple[str, Any, Any] | None:
    """The first (dotted path, run's value, rig file's value) where the run's frozen rig and
    the trusted rig file differ in DEVICE_SECTIONS (devices, camera backend and its commands,
    servo ids and models); None when they agree."""
    run = frozen.model_dump(mode="json", include=set(DEVICE_SECTIONS))
    mine = trusted.model_dump(mode="json", include=set(DEVICE_SECTIONS))
    for section in DEVICE_SECTIONS:
        found = _first_difference(run.get(section), mine.get(section), section)
        if found:
            return found
    return None
