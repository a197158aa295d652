"""`gonio plan --target`: the cheapest plan of the accuracy-vs-time study that reaches a stated
accuracy on a parameter — on the study's realistic rig when the rig file states its shared
errors (their floor included), else on the ideal rig (statistical only, the rig's certificate as
a floor when it states one)."""

from __future__ import annotations

import math
from pathlib import Path

__all__ = ["plan_for_target"]


def plan_for_target(target: str, material: str, results: Path, rig: Path | None) -> list[str]:
    """`gonio plan --target`: the study's cheapest plan for the target, on the realistic rig
    when `rig` states its shared errors, else on the ideal rig (statistical only, with the
    rig's certificate as a floor when it states one). Returns the lines to print; a target no
    plan reaches, or a study that does not hold it, is a UserError naming why."""
    from gonio.errors import UserError
    from gonio.studies.accuracy_analysis import pick_plan
    from gonio.studies.accuracy_sweep import read_csv

    lines: list[str] = []
    param, sep, value = target.partition("=")
    try:
        rel = float(value)
    except ValueError:
        rel = -1.0
    if not sep or not param or not 0 < rel < 1:
        raise UserError(f"--target {target!r}: expected PARAM=REL_ERROR with 0 < REL_ERROR < 1")
    if not results.exists():
        raise UserError(
            f"{results}: no study results; run `gonio study accuracy-vs-time --quick` first"
        )
    rows = read_csv(results)
    if not any(r["param"] == param for r in rows):
        known = ", ".join(sorted({r["param"] for r in rows}))
        raise UserError(f"--target: parameter {param!r} is not in the study (known: {known})")
    if not any(r["material"] == material for r in rows):
        raise UserError(f"--material {material!r} is not in the study")
    floor = None
    if rig is not None:
        from acquisition.config import load_rig
        from gonio.studies.accuracy_analysis import (
            shared_scale_floor,
            stated_budget,
            systematic_floor,
        )

        rig_cfg = load_rig(rig)
        stated = stated_budget(rig_cfg)
        measured = systematic_floor(rows, param)
        if measured is not None and stated.keys() - {"cert_rel_sigma"}:
            return _plan_on_realistic_rig(rows, param, rel, material, rig_cfg, stated, results)
        floor = shared_scale_floor(rig_cfg, param)
    stat_target = rel
    if floor is not None:
        if floor[0] >= rel:
            raise UserError(
                f"no plan reaches ±{100 * rel:g}% on {param} on this rig: its shared scale "
                f"uncertainty is {100 * floor[0]:.3g}% ({floor[1]}), one error for every sample "
                "that more poses or longer exposures cannot average away"
            )
        stat_target = math.sqrt(rel**2 - floor[0] ** 2)  # statistical ⊕ systematic ≤ target
    best = pick_plan(rows, param, stat_target, material)
    if best is None:
        raise UserError(
            f"no plan in the study reaches ±{100 * rel:g}% on {param} for a {material} material"
        )
    lines.append(
        f"{best['plan']}: {best['poses']} poses, {best['exposures']} exposure, "
        f"MCMC {best['mcmc_steps']} steps → expected {param} error "
        f"{100 * best['rel_error']:.2f}% (median over seeds); expected lab time "
        f"{best['lab_time_s'] / 60:.1f} min"
    )
    if floor is None:
        why = (
            "give --rig to include your rig's shared floor"
            if rig is None
            else f"your rig states no shared error that moves {param} (arm-angle errors are "
            "not in the budget yet)"
        )
        lines.append(
            "That figure is statistical only: the study's simulated rig has no instrument "
            f"errors; {why}."
        )
        from gonio.studies.accuracy_analysis import systematic_floor

        measured = systematic_floor(rows, param)
        if measured is not None:
            lines.append(
                f"On the study's realistic rig (a typical lab's shared errors) no plan gets "
                f"{param} below ±{100 * measured['floor']:.3g}%: that floor is systematic."
            )
    else:
        total = math.hypot(best["rel_error"], floor[0])
        lines.append(
            f"With this rig's shared scale uncertainty of {100 * floor[0]:.3g}% ({floor[1]}): "
            f"expected total {param} error {100 * total:.2f}% (statistical ⊕ systematic)."
        )
    return lines


_BUDGET_WORDS = {
    "cert_rel_sigma": ("certificate", lambda v: f"{100 * v:.3g} %"),
    "distance_sigma_m": ("lamp distance", lambda v: f"{1e3 * v:.3g} mm"),
    "zero_sigma_deg": ("encoder zeros", lambda v: f"{v:.3g}°"),
    "tilt_sigma_deg": ("sample tilt", lambda v: f"{v:.3g}°"),
    "play_deg": ("gears' play", lambda v: f"{v:.3g}°"),
    "sag_sigma_deg": ("arm sag", lambda v: f"{v:.3g}°"),
    "bow_sigma_m": ("sample bow", lambda v: f"{1e3 * v:.3g} mm"),
    "camera_distance_sigma_m": ("camera distance", lambda v: f"{1e3 * v:.3g} mm"),
    "flat_falloff_sigma": ("flat fall-off", lambda v: f"{100 * v:.3g} %"),
    "ambient_sigma_W_m2_sr": ("ambient light", lambda v: f"{v:.2g} W/m²/sr"),
}


def _budget_words(sizes: dict) -> str:
    return ", ".join(
        f"{word} {fmt(sizes[k])}" for k, (word, fmt) in _BUDGET_WORDS.items() if k in sizes
    )


def _plan_on_realistic_rig(rows, param, rel, material, rig_cfg, stated, results) -> list[str]:
    """`gonio plan --target` for a rig that states its shared errors: from the study's realistic
    rig, the cheapest plan whose 68 % half-width (its statistical part ⊕ the systematic part
    for this rig: the shared scale swapped for the rig's own, gonio.studies.accuracy_analysis.
    realistic_choices) and whose RMS error over the study's rigs both reach the target; or one
    line saying that no plan can, because the floor those errors leave is above the target."""
    from gonio.errors import UserError
    from gonio.studies.accuracy_analysis import realistic_choices, shared_scale_sigma
    from gonio.studies.accuracy_sweep import RECORD_NAME
    from gonio.studies.common import read_record

    lines: list[str] = []
    record = results.with_name(RECORD_NAME)
    study = read_record(record).get("realistic", {}).get("budget") if record.exists() else None
    scale_study = shared_scale_sigma(budget=study) if study else None
    scale_rig = shared_scale_sigma(rig_cfg)
    choices = realistic_choices(rows, param, scale_study, scale_rig)
    top = max(choices, key=lambda s: (s["poses"], s["lab_time_s"]))
    floor = top["rel_sys_rig"]
    words = []
    if top["scale_swapped"]:
        words.append(
            f"The shared scale is your rig's ({100 * scale_rig:.3g} %, "
            + (
                "its reference target's certificate"
                if rig_cfg.reference is not None
                else "its lamp's certificate and distance"
            )  # fmt: skip
            + f") in place of the study's ({100 * scale_study:.3g} %)."
        )
    angles = [k for k in _BUDGET_WORDS if k not in ("cert_rel_sigma", "distance_sigma_m")]
    # a study recorded before a size was budgeted states none of it (.get: 0)
    if study and any(abs(stated.get(k, 0.0) - study.get(k, 0.0)) > 1e-9 for k in angles):
        words.append(
            f"The study's realistic rig states {_budget_words(study)}; yours states "
            f"{_budget_words(stated) or 'none of these'}: the floor's part from them moves "
            "with those sizes."
        )
    if top["material"] != material:
        words.append(
            f"The realistic rig was studied on a {top['material']} material; its floor stands "
            f"in for your {material} one."
        )
    if floor >= rel:
        raise UserError(
            f"no plan reaches ±{100 * rel:g}% on {param} on this rig: its shared errors leave "
            f"±{100 * floor:.3g}% (the systematic part of the 68 % interval on the study's "
            f"largest realistic plan, {top['plan']} with {top['poses']} poses, over "
            f"{top['n']} rigs), which more poses or longer exposures cannot average away"
            + (". " + " ".join(words).rstrip(".") if words else "")
        )
    # Both the quoted uncertainty and the error the rigs really showed must meet the target
    # (a small plan's intervals can be too narrow: the study's page says where).
    ok = [s for s in choices if max(s["rel_total_rig"], s["rel_error_rig"]) <= rel]
    if not ok:
        raise UserError(
            f"no plan in the study reaches ±{100 * rel:g}% on {param} on this rig: the "
            f"largest, {top['plan']}, gives ±{100 * top['rel_total_rig']:.3g}% (of which "
            f"{100 * floor:.3g}% systematic, the floor)"
        )
    best = min(ok, key=lambda s: (s["lab_time_s"], s["compute_s"]))
    lines.append(
        f"{best['plan']}: {best['poses']} poses, {best['exposures']} exposure, "
        f"MCMC {best['mcmc_steps']} steps → expected {param} uncertainty "
        f"±{100 * best['rel_total_rig']:.2f}% (68 %, including the instrument budget: "
        f"systematic {100 * best['rel_sys_rig']:.2f}%, statistical "
        f"{100 * best['rel_stat_68']:.2f}%; RMS error {100 * best['rel_error_rig']:.2f}% "
        f"over {best['n']} simulated rigs); expected lab "
        f"time {best['lab_time_s'] / 60:.1f} min"
    )
    for line in words:
        lines.append(line)
    return lines
