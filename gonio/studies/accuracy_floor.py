"""The accuracy-vs-time page's realistic-rig section: the same plans on a rig with a typical
lab's shared errors (a fresh draw per seed), where accuracy has a floor. Every number is
computed here from the study's rows and run record."""

from __future__ import annotations

import math
from typing import Any

from gonio.studies.accuracy_analysis import summarise, systematic_floor

__all__ = ["realistic_section", "FLOOR_FACTOR"]

#: The largest plan's error must sit within this factor of the budget's systematic part for the
#: page to call it a floor (issue 17's acceptance).
FLOOR_FACTOR = 2.0

_PARAMS = ("kd", "ks", "m")


def _pct(x: float) -> str:
    return f"{100 * x:.3g}%"


def _budget_sentence(budget: dict[str, float]) -> str:
    more = [
        f"{word} {fmt(budget[key])}"
        for key, word, fmt in (
            ("bow_sigma_m", "the sample's bow", lambda v: f"{1e3 * v:.3g} mm"),
            ("camera_distance_sigma_m", "the camera's distance", lambda v: f"{1e3 * v:.3g} mm"),
            ("flat_falloff_sigma", "the flat source's fall-off", lambda v: f"{100 * v:.3g} %"),
            ("ambient_sigma_W_m2_sr", "the room's light (σ·|z|)", lambda v: f"{v:.2g} W m⁻² sr⁻¹"),
        )
        if budget.get(key)  # a record made before the size was budgeted has none
    ]
    return (
        f"the lamp's certificate {100 * budget['cert_rel_sigma']:.3g} %, its distance "
        f"{1e3 * budget['distance_sigma_m']:.3g} mm, each arm's encoder zero "
        f"{budget['zero_sigma_deg']:.3g}°, the sample's tilt {budget['tilt_sigma_deg']:.3g}° "
        f"about x and y, each axis' gear play {budget['play_deg']:.3g}° "
        f"(± {100 * budget['play_spread']:.0f} %), each elevation arm's sag "
        f"{budget['sag_sigma_deg']:.3g}°" + "".join(f", {m}" for m in more) + " (k = 1)"
    )


def budget_has_room_light(info: dict[str, Any]) -> bool:
    """Whether the study's record drew and stated the room's light (records before 2026-12-07
    did not: the rig left it unstated)."""
    return bool(info.get("budget", {}).get("ambient_sigma_W_m2_sr"))


def _handled(room_light: bool) -> str:
    """The rest of the sentence on how the fit handles the realistic rig's effects: records
    from before 2026-12-07 neither stated the room's light nor carried the bend's remainder."""
    if room_light:
        return ("the bow, camera distance, flat fall-off and room light as the fit's nuisances; "
                "the camera's non-linearity measured from the brackets, taken out, and what "
                "remains carried as a nuisance over each sample's level.")  # fmt: skip
    return ("the bow, camera distance and flat fall-off as the fit's nuisances; the camera's "
            "non-linearity measured from the brackets and taken out; the room's stray light on "
            "but not stated by this rig, so not carried.")  # fmt: skip


def realistic_section(
    rows: list[dict[str, Any]], record: dict[str, Any], png: str | None
) -> list[str]:
    """The section's lines (empty when the rows hold no realistic rig)."""
    real = {p: summarise(rows, p, "realistic") for p in _PARAMS}
    if not any(real.values()):
        return []
    info = record.get("realistic", {})
    any_s = next(s for ss in real.values() for s in ss)
    mat, exp, n = any_s["material"], any_s["exposures"], any_s["n"]
    lines = [
        "",
        "## On a realistic rig: where accuracy has a floor",
        "",
        "Every figure above is **statistical only**: the ideal rig's only errors are photon "
        "and sensor noise, so more poses always help. Here the same spine runs on a realistic "
        f"rig (configs/scenes/{info.get('scene', 'realistic')}.toml with the {mat} material, "
        f"{exp} exposures, darks and a flat field recorded), {n} rigs, each with a fresh draw "
        "of the instrument budget's shared errors — a lab's rig has one such draw for its life, "
        "so each seed is another rig (scrambled Sobol' points over the seeds). The rig file states "
        "the budget, calibration writes it into the samples, and the fit carries it as "
        "nuisance parameters; **every figure in this section includes the instrument budget**.",
        "",
    ]
    if "budget" in info:
        lines += [f"- Drawn per rig: {_budget_sentence(info['budget'])}."]
    if "stages" in info:
        light = info.get("light", {})
        lamp = (
            f"a {1e3 * light['radius_m']:.3g} mm {light['type']} lamp drifting "
            f"{100 * light['drift_per_hour']:.2g} %/h, "
            if light.get("type") == "area"
            else ""
        )
        lines += [
            f"- The same for every rig: {lamp}the simulation stages {', '.join(info['stages'])}.",
            "- How gonio handles each (docs/simulator.md): the drawn errors, the lamp's disk "
            "(the rig states its radius) and " + _handled(budget_has_room_light(info)),
        ]
    if png:
        lines += ["", f"![error vs lab time on the realistic and the ideal rig]({png})"]
    ideal = {
        (s["plan"], p): s
        for p in _PARAMS
        for s in summarise(rows, p)
        if s["material"] == mat and s["exposures"] == exp and s["axis"] == "plan"
    }
    lines += [
        "",
        "RMS error over the rigs; ±68 % is the median credible half-width, split by the fit "
        "(law of total variance over the nuisance draws) into the systematic part the budget "
        "puts there and the statistical rest; the ideal rig's error is for the same plan, "
        "material and exposures (median over its seeds).",
        "",
        "| plan | poses | lab time | compute [s] | parameter | RMS error | ±68% | systematic "
        "part | statistical part | ideal rig's error | coverage 68% / 95% |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for p in _PARAMS:
        for s in sorted(real[p], key=lambda x: x["lab_time_s"]):
            stat = math.sqrt(max(s["rel_half_width_68"] ** 2 - s["rel_sys_68"] ** 2, 0.0))
            twin = ideal.get((s["plan"], p))
            lines.append(
                f"| {s['plan']} | {s['poses']} | {s['lab_time_s'] / 60:.1f} min | "
                f"{s['compute_s']:.1f} | {p} | {_pct(s['rms_rel_error'])} | "
                f"{_pct(s['rel_half_width_68'])} | {_pct(s['rel_sys_68'])} | {_pct(stat)} | "
                f"{_pct(twin['rel_error']) if twin else '—'} | "
                f"{s['coverage_68']:.2f} / {s['coverage_95']:.2f} |"
            )
    lines += ["", *_floor_findings(rows, real, ideal)]
    return lines


def _floor_findings(rows, real, ideal) -> list[str]:  # the section's summaries
    out = []
    for p in _PARAMS:
        if not real[p]:
            continue
        floor = systematic_floor(rows, p)
        top = floor["plan"]
        low = min(real[p], key=lambda s: s["lab_time_s"])
        ratio = top["rms_rel_error"] / floor["floor"] if floor["floor"] > 0 else math.inf
        verdict = (
            f"within a factor {FLOOR_FACTOR:g} of it: the floor"
            if 1 / FLOOR_FACTOR <= ratio <= FLOOR_FACTOR
            else f"**not** within a factor {FLOOR_FACTOR:g} of it"
        )
        twin_lo, twin_hi = ideal.get((low["plan"], p)), ideal.get((top["plan"], p))
        ideal_words = (
            f" On the ideal rig the same plans take the error from {_pct(twin_lo['rel_error'])} "
            f"to {_pct(twin_hi['rel_error'])}."
            if twin_lo and twin_hi
            else ""
        )
        out.append(
            f"- **{p}**: from {low['plan']} ({low['poses']} poses) to {top['plan']} "
            f"({top['poses']} poses) lab time grows ×{top['lab_time_s'] / low['lab_time_s']:.1f}"
            f" and the RMS error goes from {_pct(low['rms_rel_error'])} to "
            f"{_pct(top['rms_rel_error'])}; the budget's systematic part on {top['plan']} is "
            f"{_pct(floor['floor'])}, and the error is {ratio:.2f}× it, {verdict}." + ideal_words
        )
    out += ["", _coverage_words(real)]
    out += [
        "",
        "Below the floor no plan helps: `gonio plan --target PARAM=REL --rig RIG.toml` with a rig "
        "that states its shared errors picks from these rows and says, in one line, when the "
        "target is below the floor. The ideal rig's recommendations below are statistical only.",
    ]
    return out


def _coverage_words(real) -> str:  # per parameter, the realistic summaries
    """Coverage pooled over the realistic plans, with the plain word where the 95 % intervals
    held the truth less often than a binomial allows (more than 2 sd below 0.95). Every plan
    runs on the same rigs, so a rig's error shows in each plan's interval alike: the pooled
    coverage's binomial sd is that of the rigs, not of the fits."""
    parts, short = [], []
    rigs = min((s["n"] for p in _PARAMS for s in real[p]), default=0)
    for p in _PARAMS:
        if not real[p]:
            continue
        n = sum(s["n"] for s in real[p])
        c68 = sum(s["coverage_68"] * s["n"] for s in real[p]) / n
        c95 = sum(s["coverage_95"] * s["n"] for s in real[p]) / n
        parts.append(f"{p} {c68:.2f} / {c95:.2f}")
        if c95 < 0.95 - 2 * math.sqrt(0.95 * 0.05 / max(rigs, 1)):
            short.append(p)
    n = sum(s["n"] for s in real[_PARAMS[0]]) if real[_PARAMS[0]] else 0
    words = (
        f"Coverage of the truth pooled over the plans ({n} fits per parameter on {rigs} rigs; "
        f"nominal 0.68 / 0.95, binomial sd over {rigs} rigs "
        f"{math.sqrt(0.68 * 0.32 / max(rigs, 1)):.2f} / "
        f"{math.sqrt(0.95 * 0.05 / max(rigs, 1)):.2f}): " + ", ".join(parts) + "."
    )
    if short:
        words += (
            f" **{', '.join(short)}: the 95 % intervals held the truth less often than they "
            "should** on these rigs — do not trust them at face value on a rig like this one "
            "(the table's RMS error against its ±68 % says by how much they are narrow)."
        )
    return words
