"""The operator: the hands a rig needs for steps no servo can do.

Calibration captures need a person: cap the lens (darks), put a uniform source in front of it
(flats), swap the sample for the reference target or a calibration board and back, switch a
lamp that has no controller. The runner asks an `Operator` before each such step and goes on
only on "yes"; "no" stops the run before anything moves (`OperatorDeclined`).

Operators here: `ConsoleOperator` (asks on the terminal; the default), `AutoOperator`
(`--yes`: the operator has prepared every step, for unattended runs), `ScriptedOperator`
(answers from a TOML file, per step). The simulator wraps any of them with hands that perform
a confirmed step in the emulated world (simulator.world), so the same questions are asked and
answered on the simulated rig.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, TextIO, runtime_checkable

from plumbing.config import ConfigError, load_config_data
from plumbing.errors import UserError

__all__ = [
    "STEP_PROMPTS",
    "OperatorStep",
    "Operator",
    "OperatorDeclined",
    "ConsoleOperator",
    "AutoOperator",
    "ScriptedOperator",
    "step",
    "load_answers",
]

# What each step asks a person to do. `{...}` fields are filled from the step's detail.
STEP_PROMPTS = {
    "cap_lens": "Put the cap on the camera lens (dark frames follow).",
    "uncap_lens": "Take the cap off the camera lens.",
    "mount_flat": (
        "Put the flat-field source (integrating sphere port or diffuser) in front of the lens."
    ),
    "unmount_flat": "Take the flat-field source away from the lens.",
    "mount_reference": "Replace the sample by the reference target ({target}), face up, centred.",
    "mount_sample": "Put the sample back in the holder, its φ = 0 mark ({mark}) along +x.",
    "mount_board": (
        "Put the calibration board {board} in the holder, centred, its x axis along +x."
    ),
    "lamp_on": "Switch the lamp on (it has no controller); the run then waits {warmup_s:g} s.",
    "lamp_off": "Switch the lamp off.",
}


@dataclass(frozen=True)
class OperatorStep:
    """A step for the operator: a machine name (`action`, a key of STEP_PROMPTS), the sentence
    shown to a person, and the details the step needs (e.g. which board)."""

    action: str
    prompt: str
    detail: dict[str, Any] = field(default_factory=dict)


def step(action: str, **detail: Any) -> OperatorStep:
    """The step named `action`, its prompt filled from `detail`."""
    try:
        template = STEP_PROMPTS[action]
    except KeyError:
        raise ValueError(f"unknown operator step {action!r}") from None
    return OperatorStep(action, template.format(**detail), dict(detail))


class OperatorDeclined(UserError, RuntimeError):
    """The operator answered "no" (or could not be asked); the run stopped before the step."""


@runtime_checkable
class Operator(Protocol):
    def confirm(self, step: OperatorStep) -> bool:
        """Ask for `step`; True once it is done, False if the operator declines."""


class AutoOperator:
    """`--yes`: every step is taken as done (for unattended runs prepared in advance)."""

    def __init__(self, log: TextIO | None = None) -> None:
        self.log = log
        self.asked: list[str] = []

    def confirm(self, step: OperatorStep) -> bool:
        self.asked.append(step.action)
        if self.log is not None:
            self.log.write(f"operator (--yes): {step.prompt}\n")
        return True


class ConsoleOperator:
    """Asks on the terminal: Enter or "y" confirms, "n" declines. With no terminal (closed
    stdin) it declines, naming `--yes` and `--answers` as the ways to run unattended."""

    def __init__(self, stdin: TextIO | None = None, stdout: TextIO | None = None) -> None:
        self.stdin = stdin or sys.stdin
        self.stdout = stdout or sys.stderr
        self.reason: str | None = None

    def confirm(self, step: OperatorStep) -> bool:
        self.stdout.write(f"\n>>> {step.prompt}\n    Done? [Y/n] ")
        self.stdout.flush()
        try:
            line = self.stdin.readline()
        except (OSError, ValueError):  # no terminal (detached, or stdin redirected away)
            line = ""
        if not line:
            self.reason = "no answer (stdin is closed); use --yes or --answers FILE"
            return False
        return line.strip().lower() in ("", "y", "yes")


def load_answers(path: Path | str) -> dict[str, bool]:
    """Answers file (TOML): `[answers]` with step names → "yes"/"no", and an optional
    `default = "yes"|"no"` for steps not listed (stored under the key "*")."""
    data = load_config_data(path)
    extra = set(data) - {"answers", "default"}
    if extra:
        raise ConfigError(f"{path}: unknown key {sorted(extra)[0]!r} (use [answers] and default)")
    out: dict[str, bool] = {}
    table = data.get("answers", {})
    if not isinstance(table, dict):
        raise ConfigError(
            f'{path}: answers must be a table of steps ([answers] with step = "yes" or '
            f'"no"), not {type(table).__name__} {table!r:.40}'
        )
    items = dict(table)
    if "default" in data:
        items["*"] = data["default"]
    for key, value in items.items():
        if key != "*" and key not in STEP_PROMPTS:
            raise ConfigError(
                f"{path}: answers.{key}: unknown step; steps are {', '.join(STEP_PROMPTS)}"
            )
        if not isinstance(value, str) or value.lower() not in ("yes", "no"):
            raise ConfigError(f'{path}: answers.{key}: must be "yes" or "no" (got {value!r})')
        out[key] = value.lower() == "yes"
    return out


class ScriptedOperator:
    """Answers from a file (`load_answers`); a step with no answer and no default declines."""

    def __init__(self, answers: dict[str, bool], source: str = "answers file") -> None:
        self.answers = dict(answers)
        self.source = source
        self.asked: list[str] = []
        self.reason: str | None = None

    @classmethod
    def from_file(cls, path: Path | str) -> ScriptedOperator:
        return cls(load_answers(path), str(path))

    def confirm(self, step: OperatorStep) -> bool:
        self.asked.append(step.action)
        if step.action in self.answers:
            return self.answers[step.action]
        if "*" in self.answers:
            return self.answers["*"]
        self.reason = f"{self.source} has no answer for step {step.action!r} and no default"
        return False


def ask(operator: Operator, s: OperatorStep) -> None:
    """Ask; raise OperatorDeclined (one line: the step, and why) unless confirmed."""
    if operator.confirm(s):
        return
    why = getattr(operator, "reason", None)
    raise OperatorDeclined(
        f"the operator declined: {s.prompt.rstrip('.')}" + (f" ({why})" if why else "")
    )
