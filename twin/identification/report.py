"""Tables and figures of an identification (3-X paper §5.3-5.5): Tables 1 and 2, Figs. 4-8.

Text tables are shaped like the paper's: Table 1 = friction by the complete model (eqs. 44-45)
and by the friction-alone model, linear stiffness and damping; Table 2 = variable stiffness k, λ
and damping. Every value has its relative σ (eq. 50); ``!`` marks a badly identified parameter.
Figures are PNG files written with matplotlib's Agg backend (no display needed).
"""

from __future__ import annotations

import io
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from twin.identification.estimators import relative_sigma_percent
from twin.identification.pipeline import Estimate, Processed, Validation

__all__ = ["report_dict", "table_1", "table_2", "tables_text", "write_figures"]


_BANDWIDTH_FROM = {"alpha_d": "the excitation α^d", "theta_dot": "the motor velocities", "given": "--cutoff-hz"}


def _cell(est: Estimate, name: str) -> tuple[str, str]:
    i = est.names.index(name)
    flag = " !" if est.badly_identified[i] else (" b" if est.at_bound[i] else "")
    return f"{est.values[i]:.4g}", f"{relative_sigma_percent(float(est.relative_sigma[i]))}{flag}"


def _method_lines(est: Estimate) -> list[str]:
    """How ``est`` was obtained, and every parameter's ±2σ interval (about 95 %)."""
    bounds = ", ".join(est.active_bounds) or "none"
    cells = [f"{n} [{lo:.4g}, {hi:.4g}]" for n, lo, hi in zip(est.names, est.ci_low, est.ci_high)]
    return [f"  {est.method}: {est.estimator}; σ {est.sigma_method}; held at a physical bound: {bounds}",
            *("    ±2σ: " + "  ".join(cells[i:i + 4]) for i in range(0, len(cells), 4))]


def table_1(estimates: Mapping[str, Estimate]) -> str:
    """Table 1: f_s by eqs. 44-45 and by eq. 38 alone, k and c_a of the linear cable model."""
    comp, fric = estimates["complete"], estimates["friction"]
    n = len(fric.names)
    head = f"{'':10s}{'eqs. 44-45':>12s}{'eq. 38':>12s} | {'stiffness':>10s}{'':>12s} | {'damping':>10s}{'':>12s}"
    lines = ["Table 1: identified parameters (linear cables)", head, "-" * len(head)]
    for j in range(1, n + 1):
        fc, rc = _cell(comp, f"f_s({j})")
        ff, rf = _cell(fric, f"f_s({j})")
        k, rk = _cell(comp, f"k({j})")
        c, rca = _cell(comp, f"c_a({j})")
        lines.append(f"{f'f_s({j}) N':10s}{fc:>12s}{ff:>12s} | {f'k({j}) N/m':>10s}{k:>12s} | {f'c_a({j}) Ns/m':>10s}{c:>12s}")
        lines.append(f"{'rel. σ':10s}{rc:>12s}{rf:>12s} | {'rel. σ':>10s}{rk:>12s} | {'rel. σ':>10s}{rca:>12s}")
    lines += _method_lines(comp) + _method_lines(fric)
    lines.append(
        f"cond(W): {comp.condition_number:.4g} (eqs. 44-45), {fric.condition_number:.4g} (eq. 38); "
        f"residual ‖ρ‖: {comp.residual_norm:.4g}, {fric.residual_norm:.4g}; rows {comp.n_rows}, {fric.n_rows}"
    )
    return "\n".join(lines)


def table_2(estimates: Mapping[str, Estimate]) -> str:
    """Table 2: k, λ and c_a of the variable stiffness model (eqs. 54-57)."""
    var = estimates["variable"]
    n = sum(name.startswith("k(") for name in var.names)  # the load-friction estimator has more than k, λ, c_a
    head = f"{'stiffness':>14s}{'':>12s} | {'stiffness':>14s}{'':>12s} | {'damping':>14s}{'':>12s}"
    lines = ["Table 2: identified parameters (variable stiffness)", head, "-" * len(head)]
    for j in range(1, n + 1):
        k, rk = _cell(var, f"k({j})")
        lam, rl = _cell(var, f"lambda({j})")
        c, rc = _cell(var, f"c_a({j})")
        lines.append(f"{f'k({j}) N/m':>14s}{k:>12s} | {f'λ({j}) 1/m':>14s}{lam:>12s} | {f'c_a({j}) Ns/m':>14s}{c:>12s}")
        lines.append(f"{'rel. σ':>14s}{rk:>12s} | {'rel. σ':>14s}{rl:>12s} | {'rel. σ':>14s}{rc:>12s}")
    lines += _method_lines(var)
    # the load-friction fit reports the largest cond of its per-cable Jacobians (columns scaled), not a W's
    cond = "cond(J, largest of the cables)" if "mu(1)" in var.names else "cond(W)"
    lines.append(f"{cond}: {var.condition_number:.4g}; residual ‖ρ‖: {var.residual_norm:.4g} N; rows {var.n_rows}; "
                 f"estimator: {var.estimator}")
    return "\n".join(lines)


def tables_text(estimates: Mapping[str, Estimate], proc: Processed, validation: Validation | None = None,
                kept_base: list[str] | None = None) -> str:
    parts = [
        f"processing: Butterworth filtfilt cutoff {proc.cutoff_hz:.2f} Hz (f_99 {proc.f_99_hz:.2f} Hz of "
        f"{_BANDWIDTH_FROM.get(proc.bandwidth_from, proc.bandwidth_from)}), "
        f"{proc.n} instants at {proc.rate_hz:.2f} Hz"
        + (f", {int(proc.fitted.sum())} fitted: {'; '.join(proc.notes)}" if not proc.fitted.all() else ""),
        "", table_1(estimates), "", table_2(estimates), "",
        f"! = badly identified (relative σ > {100 * estimates['variable'].threshold:g} %, or a value outside the "
        "physical range, or held at a physical bound by the bounded solution, or a σ that cannot be trusted on a "
        "record this short for its cutoff): never used, the base value is "
        "kept; b = at a bound; ±2σ = about 95 % confidence interval with the σ method named under each table",
    ]
    if kept_base:
        parts.append("kept at base value: " + ", ".join(kept_base))
    if validation is not None:
        parts += ["", "Validation"]
        parts.append(f"  torque mean error |Γ_m − Γ_rf| {validation.gamma_rf_error:.3f} N·m, "
                     f"|Γ_m − Γ_r| {validation.gamma_r_error:.3f} N·m (eqs. 51-53)")
        for name, err in validation.tension_error.items():
            parts.append(f"  tension mean error ({name} cables, eq. 42 both sides): {err:.2f} N")
        for (meth, model), a in validation.alpha_hat.items():
            parts.append(f"  α̂ by {meth[:2]}. {meth[2:]}, {model:8s} cables: mean error {a.mean_error_deg:.2f}° against α_IP")
    return "\n".join(parts)


def report_dict(estimates: Mapping[str, Estimate], proc: Processed, validation: Validation | None = None,
                provenance: Any = None) -> dict[str, Any]:
    """Everything of the text report as JSON-ready data (``--json``)."""
    import msgspec

    out: dict[str, Any] = {
        "processing": {"cutoff_hz": proc.cutoff_hz, "f_99_hz": proc.f_99_hz, "bandwidth_from": proc.bandwidth_from, "rate_hz": proc.rate_hz, "n": proc.n,
                       "n_fitted": int(proc.fitted.sum()), "notes": list(proc.notes)},
        "table_1": {"complete": estimates["complete"].to_dict(), "friction": estimates["friction"].to_dict()},
        "table_2": estimates["variable"].to_dict(),
    }
    if validation is not None:
        out["validation"] = validation.summary()
    if provenance is not None:
        out["provenance"] = msgspec.to_builtins(provenance)
    return out


def write_figures(validation: Validation, out_dir: str | Path) -> list[Path]:
    """Figs. 4-8 as PNG in ``out_dir``; returns the paths written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths: list[Path] = []
    t = validation.t_s
    N = validation.gamma_m.shape[1]

    fig, grid = plt.subplots(N, 1, figsize=(10, 2.4 * N), sharex=True, squeeze=False)
    axes = grid[:, 0]
    for i, ax in enumerate(axes):
        ax.plot(t, validation.gamma_m[:, i], "b", lw=0.8, label="Γ_m = Z·f")
        ax.plot(t, validation.gamma_rf[:, i], "g", lw=0.8, label="Γ_rf (friction)")
        ax.plot(t, validation.gamma_r[:, i], "r", lw=0.8, label="Γ_r (no friction)")
        ax.set_ylabel(f"joint {i + 1} (N·m)")
    axes[0].legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("t (s)")
    fig.suptitle(f"Fig. 4: torques; mean error {validation.gamma_rf_error:.3f} with friction, "
                 f"{validation.gamma_r_error:.3f} without (N·m)")
    paths.append(_save(fig, out / "fig4_torques.png", plt))

    for model, fig_name in (("linear", "fig5_tension_linear.png"), ("variable", "fig7_tension_variable.png")):
        if model not in validation.tension_force:
            continue
        tf, ts = validation.tension_force[model], validation.tension_stiffness[model]
        nc = tf.shape[1]
        fig, grid = plt.subplots(nc, 1, figsize=(10, 2.2 * nc), sharex=True, squeeze=False)
        axes = grid[:, 0]
        for j, ax in enumerate(axes):
            ax.plot(t, tf[:, j], "b", lw=0.8, label="from forces (eq. 42 RHS)")
            ax.plot(t, ts[:, j], "r", lw=0.8, label="from stiffness (eq. 42 LHS)")
            ax.set_ylabel(f"t_c{j + 1} (N)")
        axes[0].legend(loc="upper right", fontsize=8)
        axes[-1].set_xlabel("t (s)")
        fig.suptitle(f"{'Fig. 5' if model == 'linear' else 'Fig. 7'}: tension, {model} cables; "
                     f"mean error {validation.tension_error[model]:.2f} N")
        paths.append(_save(fig, out / fig_name, plt))

    fig, ax = plt.subplots(figsize=(7, 5))
    for model, color in (("linear", "b"), ("variable", "r")):
        if model in validation.tension_force:
            tf = validation.tension_force[model]
            ax.plot(tf.ravel(), np.abs(tf - validation.tension_stiffness[model]).ravel(), ".", ms=1.5, color=color,
                    label=f"{model} ({validation.tension_error[model]:.2f} N mean)")
    ax.set_xlabel("tension from the forces (N)")
    ax.set_ylabel("|reconstruction error| (N)")
    ax.legend()
    ax.set_title("Fig. 6: tension reconstruction error against tension")
    paths.append(_save(fig, out / "fig6_tension_error.png", plt))

    if validation.alpha_hat:
        fig, axes = plt.subplots(N, 2, figsize=(12, 2.4 * N), sharex=True, squeeze=False)
        colors = {"rigid": "g", "linear": "b", "variable": "r"}
        for col, meth in enumerate(("eq33", "eq35")):
            for i in range(N):
                ax = axes[i, col]
                ax.plot(validation.t_ip_s, np.degrees(validation.alpha_ip[:, i]), "k", lw=0.6, label="α_IP")
                for model, color in colors.items():
                    a = validation.alpha_hat.get((meth, model))
                    if a is not None:
                        ax.plot(a.t_s, np.degrees(a.alpha_hat[:, i]), color, lw=0.8,
                                label=f"{model} ({a.mean_error_deg:.2f}°)")
                ax.set_ylabel(f"α{i + 1} (deg)")
            axes[0, col].set_title(f"α̂ by eq. {meth[2:]}")
            axes[0, col].legend(loc="upper right", fontsize=7)
            axes[-1, col].set_xlabel("t (s)")
        fig.suptitle("Fig. 8: reconstruction of α (mean errors against α_IP)")
        paths.append(_save(fig, out / "fig8_alpha_hat.png", plt))
    return paths


def _save(fig: Any, path: Path, plt: Any) -> Path:
    from bridge.archive import atomic_write

    fig.tight_layout()
    # Written whole (bridge.archive.atomic_write): a full disk or a Ctrl-C leaves the previous
    # figure or none, never a truncated PNG.
    buffer = io.BytesIO()
    try:
        fig.savefig(buffer, dpi=110, format=path.suffix.lstrip(".") or "png")
    finally:
        plt.close(fig)
    atomic_write(path, buffer.getvalue())
    return path
