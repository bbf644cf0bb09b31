"""Does the identified parameter set control better than the prototype's, on the robot truth?

Runs the users' commands as subprocesses and writes docs/identification/identified-set-control.md:

1. ``xneck campaign identification --seed S --out RUNS/ident-S.mcap --json`` (law 1's §5.2.2
   campaign on the robot truth; it writes the identified set beside the archive);
2. ``xneck campaign control --law L --seed C --truth robot --json`` with the prototype's set, with
   ``--params`` the identified set, and with the identified set plus the output error's spring
   rates and pulley radius (the ``--set`` line the identified file's header prints).

The twin's robot is the prototype's whatever set the controller is given (twin/sim/truth.py,
``robot_params``); before 2026-11-27 it was rebuilt from the controller's set, and this comparison
could not be made. Archives go to a temporary directory (``--keep DIR`` keeps them).

    nice -n 5 .venv/bin/python docs/identification/identified_set_control.py --ident-seeds 0,1 --control-seeds 1,2,3
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
XNECK = [sys.executable, "-m", "server.cli"]
OUT = Path(__file__).with_name("identified-set-control.md")


def run(args: list[str], data_dir: Path) -> dict:
    """One xneck command's JSON (exits on failure with its stderr)."""
    done = subprocess.run([*XNECK, *args], cwd=ROOT, capture_output=True, text=True,
                          env={**__import__("os").environ, "XNECK_DATA_DIR": str(data_dir)})
    if done.returncode != 0:
        sys.exit(f"xneck {' '.join(args)} failed ({done.returncode}):\n{done.stderr[-2000:]}")
    return json.loads(done.stdout)


def structure_sets(identified: Path) -> list[str]:
    """The ``--set`` values of the identified file's header line (twin.identification.pipeline)."""
    line = next((x for x in identified.read_text().splitlines() if "to apply them:" in x), "")
    return [part.strip().strip("'") for part in line.split("--set")[1:]]


def git_head() -> str:
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT, capture_output=True,
                           text=True).stdout.strip()
    return head + ("-dirty" if dirty else "")


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--ident-seeds", default="0,1", help="identification campaign seeds, comma-separated")
    ap.add_argument("--control-seeds", default="1,2,3", help="control campaign seeds (sensor noise), comma-separated")
    ap.add_argument("--laws", default="2,3", help="control laws, comma-separated")
    ap.add_argument("--keep", type=Path, default=None, help="keep the archives in this directory")
    ap.add_argument("--out", type=Path, default=OUT, help="the page to write")
    args = ap.parse_args()
    ident_seeds = [int(s) for s in args.ident_seeds.split(",")]
    control_seeds = [int(s) for s in args.control_seeds.split(",")]
    laws = [int(s) for s in args.laws.split(",")]
    started, head = time.monotonic(), git_head()
    with tempfile.TemporaryDirectory(prefix="xneck-identified-set-") as tmp:
        runs = args.keep or Path(tmp)
        runs.mkdir(parents=True, exist_ok=True)
        variants: dict[str, list[str]] = {"prototype": []}
        notes: list[str] = []
        for s in ident_seeds:
            archive = runs / f"ident-{s}.mcap"
            report = run(["campaign", "identification", "--seed", str(s), "--out", str(archive), "--json"], runs)
            identified = next((archive.parent / f"{archive.stem}_identification").glob("*-identified.toml"))
            sets = structure_sets(identified)
            variants[f"identified (seed {s})"] = ["--params", str(identified)]
            variants[f"identified + structure (seed {s})"] = ["--params", str(identified),
                                                              *[a for v in sets for a in ("--set", v)]]
            k = {r["name"]: r["estimate"] for r in report["provenance"]["parameters"]}
            notes.append(f"- seed {s}: `xneck campaign identification --seed {s} --out ident-{s}.mcap --json`; "
                         f"structure `{' '.join(f'--set {v}' for v in sets)}`; variable k (N/m) "
                         + ", ".join(f"{k[f'cables.variable.k({j})']:.0f}" for j in range(1, 5)) + ", λ (1/m) "
                         + ", ".join(f"{k[f'cables.variable.lambda({j})']:.1f}" for j in range(1, 5)))
            print(notes[-1], flush=True)
        table: dict[tuple[int, str], list[tuple[float, float]]] = {}
        for law in laws:
            for name, extra in variants.items():
                for c in control_seeds:
                    m = run(["campaign", "control", "--law", str(law), "--seed", str(c), "--truth", "robot",
                             *extra, "--json"], runs)["metrics"]
                    table.setdefault((law, name), []).append((m["e_mean_all_deg"], m["e_alpha_mean_all_deg"]))
                    print(f"law {law} {name} seed {c}: e {m['e_mean_all_deg']:.3f}°, e_α {m['e_alpha_mean_all_deg']:.3f}°",
                          flush=True)
    lines = [
        "# Controlling with the identified set, on the robot truth",
        "",
        f"Written by `docs/identification/identified_set_control.py --ident-seeds {args.ident_seeds} "
        f"--control-seeds {args.control_seeds} --laws {args.laws}` at `{head}` "
        f"({(time.monotonic() - started) / 60:.0f} min wall), which runs the commands below as a user would.",
        "",
        "The twin's robot stays the prototype's (its Table 2 k and λ, the robot truth's deviations) whatever set",
        "the controller is given (`robot_params` in twin/sim/robot_truth.toml). Identified sets:",
        "",
        *notes,
        "",
        "Then `xneck campaign control --law L --seed C --truth robot --json` with each set (`--params FILE`, and the",
        "structure's `--set` values), C ∈ {" + args.control_seeds + "}: mean tracking error e and estimation error",
        "e_α over the §7 test (°), each seed's value and their mean.",
        "",
        "| law | controller's set | e per seed (°) | mean e (°) | e_α per seed (°) | mean e_α (°) |",
        "|---|---|---|---|---|---|",
    ]
    for (law, name), values in table.items():
        e, ea = [v[0] for v in values], [v[1] for v in values]
        lines.append(f"| {law} | {name} | {', '.join(f'{x:.3f}' for x in e)} | {statistics.mean(e):.3f} | "
                     f"{', '.join(f'{x:.3f}' for x in ea)} | {statistics.mean(ea):.3f} |")
    lines += ["", *summary(table, laws), ""]
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")


def summary(table: dict[tuple[int, str], list[tuple[float, float]]], laws: list[int]) -> list[str]:
    """Means over the identified sets, against the prototype's and the control seeds' spread."""
    out = ["Means over the identified sets (numbers from the table; the spread is the prototype's max − min",
           "over the control seeds, which change only the sensors' noise):", ""]
    for law in laws:
        def mean(kind: str, i: int) -> float:
            return statistics.mean(v[i] for (lw, name), vs in table.items() for v in vs
                                   if lw == law and name.split(" (")[0] == kind)

        proto = [v for v in table[(law, "prototype")]]
        spread = [max(v[i] for v in proto) - min(v[i] for v in proto) for i in (0, 1)]
        out.append(f"- law {law}: e {mean('prototype', 0):.3f}° (prototype) → {mean('identified', 0):.3f}° (identified) → "
                   f"{mean('identified + structure', 0):.3f}° (+ structure), spread {spread[0]:.3f}°; e_α "
                   f"{mean('prototype', 1):.3f}° → {mean('identified', 1):.3f}° → {mean('identified + structure', 1):.3f}°, "
                   f"spread {spread[1]:.3f}°")
    out += ["", "Reading (words written 2026-11-27, on the run of that day): the identified k and λ help law 3, which",
            "uses them (its e falls by about 14 %); law 2 uses no cable stiffness and barely changes. The output",
            "error's spring rates and pulley radius lower law 2's e_α by a few hundredths of a degree on every run",
            "and leave law 3 within the spread. They are effective values (the rates absorb the bar masses' and free",
            "lengths' errors, which the fit holds), not the springs' physical rates that a parameter file holds and",
            "the workspace and stiffness analyses read: `xneck identify` reports them with the `--set` line that",
            "applies them and does not write them into the set."]
    return out


if __name__ == "__main__":
    main()
