"""Regenerate docs/twin-fidelity.md: what each effect of the robot truth (twin/sim/truth.py,
twin/sim/robot_truth.toml) changes on the §7 control test and on the identification, alone and
all together, beside the 3-X paper's prototype numbers.

Runs in process what the users' commands run over the bus: ``xneck campaign control --twin
--truth robot --law 1|2|3 [--no-pulleys]`` is controller.offline.run_closed_loop (the same loop as
the lockstep campaign, though not the same digits on the robot truth: the module's table says by how
much) against a twin of the truth; ``xneck campaign identification --twin --truth
robot`` is law 1 on the §5.2.2 cycloids the same way, its α_IP measured on rendered frames
(controller.identification_loop.law1_campaign), then the identification pipeline.
"Each effect alone" is the robot truth with only that section enabled (``RobotTruth.only``), the
same as a truth file with the other sections' ``enabled = false``. Serial, about 3 minutes on a
2-core machine (181 s on 2026-11-26; 924 s on 2026-11-27 on a slower VM with another job beside). Run:
``.venv/bin/python docs/make_twin_fidelity.py``.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from controller.identification_loop import law1_campaign
from controller.laws import LawConfig
from controller.offline import run_closed_loop
from controller.trajectory import control_test_trajectory
from twin.identification.model_choice import auto_choice
from twin.identification.pipeline import (
    identified_params,
    identify_all,
    identify_friction,
    identify_variable,
    make_provenance,
    preprocess,
    validate,
)
from twin.model.params import load_params
from twin.sim.simulator import TwinConfig
from twin.sim.truth import EFFECTS, load_truth

DOCS = Path(__file__).resolve().parent
ROOT = DOCS.parent
PAPER = {"law1": (0.52, 2.19), "law2": (0.37, 1.51), "law3": (0.66, 1.09)}  # §7: mean e, e_α (deg), prototype
PAPER_GAMMA_RF = 0.18  # N·m, §5.3: mean |Γ_m − Γ_rf| on the prototype
LAWS = {"law1": LawConfig(law=1), "law2": LawConfig(law=2), "law3": LawConfig(law=3),
        "no pulleys": LawConfig(law=2, no_pulleys=True)}
SEED = 11
# Values with no source ("none" in robot_truth.toml): the range over which the conclusions are checked.
# (Each row costs four §7 runs: only the two unsourced values that move the results most here.)
RANGES = [
    ("friction", "stribeck_velocity_rad_s", (0.5, 5.0)),
    ("cables", "creep_ratio", (0.0, 0.10)),
]
# Unsourced values ("none:" in robot_truth.toml) against issue 16's identification target: zero and
# twice the guess (a spread doubled about 1), each on IDENT_SEEDS campaigns.
IDENT_RANGES = [
    ("friction", "asymmetry", ((0.0, 0.0, 0.0, 0.0), (0.10, -0.10, 0.10, -0.10))),
    ("friction", "stribeck_velocity_rad_s", (0.5, 5.0)),
    ("cables", "creep_ratio", (0.0, 0.10)),
    ("cables", "creep_time_s", (0.5, 8.0)),
    ("actuation", "torque_constant_factor", ((1.0, 1.0, 1.0, 1.0), (1.042, 0.936, 1.074, 0.982))),
    ("actuation", "cogging_N", (0.0, 3.2)),
]
IDENT_SEEDS = (0, 1, 2)


def control(truth) -> dict[str, dict]:
    traj = control_test_trajectory()
    params = load_params()
    return {name: run_closed_loop(params, law, traj, TwinConfig(seed=SEED, truth=truth)).metrics()
            for name, law in LAWS.items()}


def identification(truth) -> dict[str, Any]:
    base = load_params()
    data = law1_campaign(0, truth, base)
    proc = preprocess(data, base)
    est = identify_all(proc, base)
    new, _, _ = identified_params(base, est, make_provenance(data.campaign, proc))
    val = validate(data, proc, new, est)
    var = est["variable"]
    # what `xneck identify` reports by default: the load-friction fit where it rejects eqs. 54-55
    auto = identify_variable(proc, base, est["friction"].values, estimator="auto")
    return {
        "f_s": est["friction"].values / np.array(base.friction.f_s) - 1,
        "k": var.vector("k") / np.array(base.cables.variable.k) - 1,
        "lam": var.vector("lambda") / np.array(base.cables.variable.lam) - 1,
        "gamma_rf": float(val.gamma_rf_error),
        "auto": auto_choice(auto.estimator)[0],
        "k_auto": auto.vector("k") / np.array(base.cables.variable.k) - 1,
        "lam_auto": auto.vector("lambda") / np.array(base.cables.variable.lam) - 1,
    }


def table2_auto(truth) -> dict[str, Any]:
    """Table 2 as `xneck identify` reports it by default (`--estimator auto`) on :data:`IDENT_SEEDS`
    campaigns of ``truth``: which estimator it chose, how many of the k and λ are within 10 %, the
    largest errors and the misses."""
    base = load_params()
    truth_k, truth_lam = np.array(base.cables.variable.k), np.array(base.cables.variable.lam)
    chosen, errors, misses = set(), [], []
    for seed in IDENT_SEEDS:
        proc = preprocess(law1_campaign(seed, truth, base), base)
        auto = identify_variable(proc, base, identify_friction(proc, base).values, estimator="auto")
        chosen.add(auto_choice(auto.estimator)[0])
        err = np.r_[auto.vector("k") / truth_k - 1, auto.vector("lambda") / truth_lam - 1]
        errors.append(err)
        names = [f"k({j + 1})" for j in range(4)] + [f"λ({j + 1})" for j in range(4)]
        misses += [f"{n} {100 * e:+.0f} %" for n, e in zip(names, err) if abs(e) >= 0.10]
    e = np.abs(np.asarray(errors))
    return {"chosen": ", ".join(sorted(chosen)), "within": int(np.sum(e < 0.10)), "of": e.size,
            "k_max": float(e[:, :4].max()), "lam_max": float(e[:, 4:].max()), "misses": misses}


def findings(m: dict[str, dict]) -> dict[str, bool]:
    e = {k: v["e_mean_all_deg"] for k, v in m.items()}
    ea = {k: v["e_alpha_mean_all_deg"] for k, v in m.items()}
    factor2 = all(0.5 < e[k] / PAPER[k][0] < 2 and 0.5 < ea[k] / PAPER[k][1] < 2 for k in PAPER)
    return {
        "law 2 tracks best": e["law2"] < min(e["law1"], e["law3"]),
        "law 3 estimates best": ea["law3"] < min(ea["law1"], ea["law2"]),
        "pulleys matter": e["no pulleys"] > e["law2"] and ea["no pulleys"] > ea["law2"],
        "within ×2 of the prototype": factor2,
    }


def _yes(b: bool) -> str:
    return "yes" if b else "**no**"


def main() -> None:
    t0 = time.time()
    robot = load_truth("robot")
    configs = [("none (`--truth model`)", robot.only())] + [(f"{e} alone", robot.only(e)) for e in EFFECTS]
    configs.append(("all (`--truth robot`)", robot))
    results, ident, ranges, ident_ranges = {}, {}, [], []
    for label, truth in configs:
        results[label] = control(truth)
        print(f"[{time.time() - t0:5.0f} s] control: {label}", flush=True)
        write(results, ident, ranges)
    for label, truth in (configs[0], configs[1], configs[-1]):
        ident[label] = identification(truth)
        print(f"[{time.time() - t0:5.0f} s] identification: {label}", flush=True)
        write(results, ident, ranges)
    for section, key, values in RANGES:
        for value in values:
            truth = robot.replace(section, **{key: value})
            ranges.append((f"{section}.{key} = {value}", findings(control(truth))))
            print(f"[{time.time() - t0:5.0f} s] range: {section}.{key} = {value}", flush=True)
            write(results, ident, ranges)
    ident_ranges.append(("(the default robot truth)", table2_auto(robot)))
    for section, key, values in IDENT_RANGES:
        for value in values:
            label = f"{section}.{key} = {list(value) if isinstance(value, tuple) else value}"
            ident_ranges.append((label, table2_auto(robot.replace(section, **{key: value}))))
            print(f"[{time.time() - t0:5.0f} s] identification range: {label}", flush=True)
            write(results, ident, ranges, ident_ranges)
    print(f"wrote {DOCS / 'twin-fidelity.md'} in {time.time() - t0:.0f} s")


def write(results: dict, ident: dict, ranges: list, ident_ranges: list | None = None) -> None:
    """docs/twin-fidelity.md from what has run so far (rewritten after every stage)."""
    lines = [
        "# Twin fidelity: the robot's unmodelled physics beside the 3-X prototype",
        "",
        "Regenerated by `docs/make_twin_fidelity.py`, in process (`run_closed_loop`: the controller's and the twin's",
        "code without the bus). The bus campaigns, `xneck campaign control --twin --truth robot --law 1|2|3",
        "[--no-pulleys]` and `xneck campaign identification --twin --truth robot`, run the same code over Zenoh and",
        "land close but not on the same digits on the robot truth (`--seed 11`: law 2 e 0.49, e_α 1.51, mean force",
        "23.0; law 3 0.92 / 1.11 / 24.5; audit of 2026-11-29).",
        "The controller always runs the paper's model (prototype_3x.toml); the twin runs a *truth*:",
        "the model plus the effects of `twin/sim/robot_truth.toml`, each with its source there",
        "(datasheet / measurement / physics estimate / architecture / none). Values are chosen from those",
        "sources, not fitted to the tables below. Angles in degrees, forces in N; §7 control test, seed 11;",
        "e = mean |α^d − α̂|, e_α = mean |α̂ − α_IP| (camera σ = 1°, so e_α ≥ about 0.8° whatever the truth).",
        "",
        "## §7 control test: each effect alone and all together",
        "",
        "| truth | law 1 e | law 2 e | law 3 e | no-pulleys e | law 1 e_α | law 2 e_α | law 3 e_α | no-pulleys e_α "
        "| mean force law 1/2/3 | saturated ticks law 1/2/3 |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for label, m in results.items():
        e = [m[k]["e_mean_all_deg"] for k in LAWS]
        ea = [m[k]["e_alpha_mean_all_deg"] for k in LAWS]
        f = [m[k]["force_mean_all_N"] for k in ("law1", "law2", "law3")]
        sat = [m[k]["saturated_ticks"] for k in ("law1", "law2", "law3")]
        lines.append(f"| {label} | " + " | ".join(f"{x:.2f}" for x in e + ea)
                     + f" | {f[0]:.1f} / {f[1]:.1f} / {f[2]:.1f} | {sat[0]} / {sat[1]} / {sat[2]} |")
    lines.append("| **prototype (§7)** | 0.52 | 0.37 | 0.66 | – | 2.19 | 1.51 | 1.09 | – | – | – |")
    lines += [
        "",
        "## The paper's findings on each truth",
        "",
        "| truth | law 2 tracks best | law 3 estimates best | pulleys matter | e and e_α within ×2 of the prototype |",
        "|---|---|---|---|---|",
    ]
    for label, m in results.items():
        lines.append(f"| {label} | " + " | ".join(_yes(v) for v in findings(m).values()) + " |")
    lines += [
        "",
        "## Identification (law 1's §5.2.2 campaign, seed 0, as `xneck campaign identification` runs it):",
        "relative error of the identified values against",
        "the truth's Table 1 f_s and Table 2 k, λ; Γ_rf residual (mean |Γ_m − Γ_rf|, N·m; prototype 0.18).",
        "The paper's pipeline (IDIM-IV, eqs. 44-45, 55), then Table 2 as `xneck identify` reports it by default",
        "(`--estimator auto`: where the friction grows with the load, the neck's output error if the line's damping",
        "is light, else the load-friction fit; IDIM-IV where it does not):",
        "",
        "| truth | f_s error | k error | λ error | Γ_rf residual | `auto` chose | k error, `auto` | λ error, `auto` |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for label, r in ident.items():
        fmt = lambda v: ", ".join(f"{100 * x:+.0f} %" for x in v)  # noqa: E731
        lines.append(f"| {label} | {fmt(r['f_s'])} | {fmt(r['k'])} | {fmt(r['lam'])} | {r['gamma_rf']:.3f} "
                     f"| {r['auto']} | {fmt(r['k_auto'])} | {fmt(r['lam_auto'])} |")
    lines += [
        "",
        "## Values without a source: do the findings hold over a range?",
        "",
        "Each row is the full robot truth with one unsourced value changed.",
        "",
        "| change | law 2 tracks best | law 3 estimates best | pulleys matter | within ×2 |",
        "|---|---|---|---|---|",
    ]
    for label, f in ranges:
        lines.append(f"| `{label}` | " + " | ".join(_yes(v) for v in f.values()) + " |")
    if ident_ranges:
        lines += [
            "",
            "## Values without a source: does identification keep Table 2 within 10 %?",
            "",
            "Issue 16's target. Each row is the full robot truth with one unsourced value at zero or twice the",
            "guess; Table 2 as `xneck identify` reports it by default (`--estimator auto`), on law 1's §5.2.2",
            "campaign (what `xneck campaign identification` runs; in process, α_IP from rendered frames), seeds",
            f"{', '.join(map(str, IDENT_SEEDS))}: 8 values per campaign.",
            "",
            "| change | `auto` chose | k, λ within 10 % | largest \\|k error\\| | largest \\|λ error\\| | misses |",
            "|---|---|---|---|---|---|",
        ]
        for label, r in ident_ranges:
            lines.append(f"| `{label}` | {r['chosen']} | {r['within']}/{r['of']} | {100 * r['k_max']:.0f} % "
                         f"| {100 * r['lam_max']:.0f} % | {', '.join(r['misses']) or '–'} |")
        full = all(r["within"] == r["of"] for _, r in ident_ranges)
        if len(ident_ranges) > 2 and full:
            k_worst = max(ident_ranges, key=lambda lr: lr[1]["k_max"])
            lam_worst = max(ident_ranges, key=lambda lr: lr[1]["lam_max"])
            chosen = sorted({c for _, r in ident_ranges for c in r["chosen"].split(", ")})
            lines += ["", f"Every row keeps {ident_ranges[0][1]['of']}/{ident_ranges[0][1]['of']} within 10 %, the default "
                      f"robot truth and each unsourced value changed (largest |k error| {100 * k_worst[1]['k_max']:.0f} % "
                      f"at `{k_worst[0]}`, |λ error| {100 * lam_worst[1]['lam_max']:.0f} % at `{lam_worst[0]}`; `auto` chose "
                      f"{', '.join(chosen)}). With the neck's output error the target no longer rests on the friction's "
                      "guessed direction asymmetry or the creep, which pulled the load-friction fit's λ(3) 10-22 % low "
                      "(docs/identification-coverage.md); it rests on a light line damping (the output error's "
                      "quasi-static pose, which `auto` checks) instead."]
        elif len(ident_ranges) > 2:
            default, rest = ident_ranges[0][1], sorted(ident_ranges[1:], key=lambda lr: lr[1]["within"])
            lines += ["", f"The default robot truth keeps {default['within']}/{default['of']} within 10 %; over the "
                      f"unsourced values the count runs {rest[0][1]['within']}-{rest[-1][1]['within']}/{default['of']}. "
                      f"Fewest: `{rest[0][0]}` ({rest[0][1]['within']}), `{rest[1][0]}` ({rest[1][1]['within']}). "
                      "So whether the target holds rests on values the robot truth guesses: the load-friction model "
                      "has no direction asymmetry of the friction (a constant offset trades against k and λ, "
                      "docs/identification-coverage.md), and a creep as fast as 0.5 s (the shortest τ its grid tries) fits worst. "
                      "A calibration on the prototype's recordings (`xneck twin calibrate`, below) is what would pin them."]
    lines += ["", *notes(results, ranges, ident), ""]
    doc = DOCS / "twin-fidelity.md"
    # The calibration section is written from `xneck twin calibrate` runs (it says which), not by this
    # script: keep it as it is.
    kept = doc.read_text().partition(CALIBRATION_HEADING)[2] if doc.exists() else ""
    doc.write_text("\n".join(lines) + (CALIBRATION_HEADING + kept if kept else ""))


CALIBRATION_HEADING = "\n## Calibration on recorded campaigns"


MODEL, ROBOT = "none (`--truth model`)", "all (`--truth robot`)"


def notes(results: dict, ranges: list, ident: dict | None = None) -> list[str]:
    """The reading of the tables, its numbers taken from them (the words were written 2026-11-25);
    while the tables are still incomplete (the script writes after every stage), nothing."""
    need = (MODEL, "actuation alone", "cables alone", ROBOT)
    if not all(k in results for k in need):
        return []
    e = {t: {k: results[t][k]["e_mean_all_deg"] for k in LAWS} for t in need}
    ea = {t: {k: results[t][k]["e_alpha_mean_all_deg"] for k in LAWS} for t in need}
    r, m = e[ROBOT], e[MODEL]

    def worse(law: str) -> str:
        return f"{100 * (r[law] / PAPER[law][0] - 1):.0f} %"

    flips = sorted({name for label, f in ranges if label.startswith("cables.creep_ratio = 0.0")
                    for name, ok in f.items() if not ok and findings(results[ROBOT])[name]})
    pulleys = (f"\"Pulleys matter\" holds robustly for e_α ({ea[ROBOT]['no pulleys']:.2f}° against "
               f"{ea[ROBOT]['law2']:.2f}°) but only marginally for e ({r['no pulleys']:.3f}° against {r['law2']:.3f}°)")
    flip_text = (f"with creep_ratio = 0, {' and '.join(flips)} flip (range table), so they rest on an unsourced value"
                 if flips else "they hold with creep_ratio = 0 and 0.1 (range table)")
    return [
        "## Reading the tables (numbers from the tables above; words written 2026-11-25)",
        "",
        "- **Friction explains the tracking gap.** The model's truth has the controller's own arctan friction,",
        f"  so laws 2 and 3 compensate it perfectly (e {m['law2']:.2f}° and {m['law3']:.2f}° against the prototype's "
        f"{PAPER['law2'][0]:.2f}° and {PAPER['law3'][0]:.2f}°).",
        "  The robot's friction alone (stiction 1.3× Coulomb, Stribeck, gear and pulley losses that grow with the",
        "  load, direction asymmetry) brings every law within ×2 of the prototype and keeps the paper's three",
        f"  findings. Law 1 hardly changes ({m['law1']:.2f} → {r['law1']:.2f}°): it has no friction model to be wrong.",
        f"- **Cable damping and creep explain part of the e_α gap** (law 2: {ea[MODEL]['law2']:.2f} → "
        f"{ea['cables alone']['law2']:.2f}°): the rigid-cable α̂ of",
        "  laws 1-2 misses the stretch of a lightly damped, creeping line. Actuation errors (k_t spread, ripple,",
        f"  cogging) add about {e['actuation alone']['law2'] - m['law2']:.2f}° to law 2's e. Structure errors, the "
        "one-tick delay and 0.1 ms jitter barely",
        "  matter at the outer loop's ω = 11 rad/s; so does the current loop above about 10 Hz (at 2 Hz law 2's",
        "  e grows 2.7×, tests/test_truth.py).",
        f"- **What does not close:** e_α stays below the prototype for law 1 ({ea[ROBOT]['law1']:.2f}° against "
        f"{PAPER['law1'][1]:.2f}°); the camera's",
        f"  bias and calibration errors are not simulated here (camera issue). Law 3 tracks {worse('law3')} worse than the",
        f"  prototype ({r['law3']:.2f}° against {PAPER['law3'][0]:.2f}°), law 2 {worse('law2')} worse ({r['law2']:.2f}° "
        f"against {PAPER['law2'][0]:.2f}°). {pulleys};",
        f"  {flip_text}.",
        *law2_note(results[ROBOT]),
        *identification_notes(ident or {}),
    ]


def law2_note(robot: dict) -> list[str]:
    """A note when law 2 does not track best on the whole robot truth (words written 2026-11-29,
    session 41, when the offline loop began to pass the law each state's stamp)."""
    if findings(robot)["law 2 tracks best"]:
        return []
    e = {k: robot[k]["e_mean_all_deg"] for k in ("law1", "law2")}
    f = {k: robot[k]["force_mean_all_N"] for k in ("law1", "law2")}
    return [
        f"- **Law 2 does not track best on the whole robot truth** (law 1 {e['law1']:.2f}° against law 2's "
        f"{e['law2']:.2f}°; law 2's mean force {f['law2']:.1f} N against law 1's {f['law1']:.1f} N), though",
        "  each effect alone keeps the finding (table) and the prototype's law 2 led law 1 by 0.15°. The offline",
        "  loop had shown law 2 ahead only while it ran the law on a fixed period, which read the twin's timing",
        "  jitter as velocity and hurt law 1 most; it now passes each state's stamp, as the bus controller does.",
    ]


def _span(x) -> str:
    x = 100 * np.asarray(x)
    return f"{x.min():+.0f} … {x.max():+.0f} %"


def identification_notes(ident: dict) -> list[str]:
    """The identification bullet of the reading, its numbers from the identification table."""
    if ROBOT not in ident or "friction alone" not in ident:
        return []
    rb, fr = ident[ROBOT], ident["friction alone"]
    return [
    "- **Identification does not keep its known answer with the robot's friction.** The paper's arctan",
    f"  regressor (eqs. 44-45, 55) fits f_s within {_span(rb['f_s'])} of Table 1, but the tensions it reconstructs",
    f"  carry the friction-shape error, and k comes out {_span(rb['k'])}, λ {_span(rb['lam'])} off",
    f"  (law 1's campaign); the Γ_rf residual is {rb['gamma_rf']:.2f} N·m against the prototype's 0.18.",
    f"  The default `auto` takes `{rb['auto']}` there: k {_span(rb['k_auto'])}, λ",
    f"  {_span(rb['lam_auto'])} on this campaign; over 20-seed runs docs/identification-coverage.md (\"`auto`",
    "  takes the output error\"). On the friction-alone row: that truth keeps the model's cable damping",
    "  (3000 N·s/m, against the line's 40 N·s/m in the robot truth), too heavy for the output error's",
    f"  quasi-static pose, and `auto` takes `{fr['auto']}` there, which trades the damping against a",
    f"  spurious creep (k {_span(fr['k_auto'])}, IDIM-IV's {_span(fr['k'])}).",
    "  The prototype's well-identified Table 2 and its",
    "  smaller residual say its friction is closer to eq. 37 near θ̇ = 0 than this set-valued Coulomb law",
    "  (pre-sliding compliance of gear and line would smooth it); this is the truth's weakest part and the",
    "  first thing a calibration on recorded campaigns should fit (`xneck twin calibrate`, below).",
    "  The output error (the neck's pose simulated from the encoders, fitted with the forces, the springs'",
    "  rates and the pulleys' radius) is free of the friction model: on law 1's robot-truth campaigns never",
    "  used in development it kept every k and λ within 5.5 % and its ±2σ covered 97-99 %",
    "  (docs/identification-coverage.md, \"The pulleys' radius fitted\").",
    "- Speed: `benchmarks/twin_speed.py` prints the tick cost with every effect off, each alone and all on",
    "  (figures in the calibration section below).",
]


if __name__ == "__main__":
    main()
