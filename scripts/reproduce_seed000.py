"""Reproduce seed 000's simulation (Gomez-Casasola & Rodriguez-Cortes, sec. 4, Figs. 1-2).

The simulator's ``circle`` scenario is the paper's: a quadrotor tracking a circle (radius 2 m,
1 m/s) with initial body velocity ``u(0) = 0.2``, ``v(0) = -0.2`` m/s, SLAM positions with per-axis
scale ``kx = 0.3``, ``ky = 0.2``; observer gains ``gamma_v = 7``, ``gamma_k = 8``, initial
``V_hat(0) = 0``, ``K_hat(0) = 0``. The drag coefficient ``mu/m`` is the simulator's (the paper
assumes it known).

1. Noise-free (and no SLAM scale drift, as in the paper): velocity error ``V - eta`` (Fig. 1) and
   scale error ``K - xi`` (Fig. 2) decay to zero, velocity first; both the published observer and
   the full-kinematics variant. Plots are saved as PNG (paths printed).
2. Noisy sensors (simulator defaults): steady-state errors (t > 20 s) are printed, for the paper's
   gains and for a lower scale gain.

Usage: ``python scripts/reproduce_seed000.py [--seed 0] [--out out/seed000]``
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from fgnav.datasets.simulate import SimOptions, simulate

from fgnav.frontends.ii_observer import IIObserverOptions, run_ii_observer

#: Steady state starts here [s] (the paper's figures settle within ~10 s).
STEADY_T = 20.0


def errors(flight, options: IIObserverOptions):
    """Run the observer; return (t, velocity error (N, 2) [m/s], scale error (N, 2) [-])."""
    res = run_ii_observer(flight, options)
    gt = flight.ground_truth
    body_v = np.einsum("nji,nj->ni", gt.world_R_body(), gt.world_v_body)
    truth = flight.meta["truth"]["slam_sessions"]["0"]
    K = (
        np.asarray(truth["axis_scale"][:2])
        * (1.0 + truth["scale_drift_per_s"] * (res.t - truth["t_start"]))[:, None]
    )
    return res.t, body_v[:, :2] - res.eta, K - res.xi, K


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("out/seed000"))
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    clean = simulate(
        "circle", args.seed, SimOptions(noise_free=True, images=False, slam_scale_drift_per_s=0.0)
    )
    drag = tuple(clean.meta["truth"]["drag_k"])
    print(f"circle, noise-free: drag mu/m = {drag} 1/s, gains 7 / 8")
    for kin in ("published", "full"):
        t, ev, ek, K = errors(clean, IIObserverOptions(kinematics=kin, drag_k=drag))
        rel = np.abs(ek) / K
        t_v = t[np.argmax(np.all(np.abs(ev) < 0.01, axis=1))]
        t_k = t[np.argmax(np.all(rel < 0.01, axis=1))]
        late = t > STEADY_T
        print(
            f"  {kin:9s}: |V~| < 1 cm/s from t = {t_v:.2f} s, |K~|/K < 1 % from t = {t_k:.2f} s; "
            f"t > {STEADY_T:.0f} s: max |V~| {np.abs(ev[late]).max() * 1000:.2f} mm/s, "
            f"max |K~|/K {100 * rel[late].max(axis=0).round(4)} %"
        )
        fig, axes = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
        axes[0].plot(t, ev[:, 0], "r", label="x")
        axes[0].plot(t, ev[:, 1], "b", label="y")
        axes[0].set_ylabel("V - eta [m/s]")
        axes[0].set_title(f"Fig. 1: velocity error ({kin})")
        axes[1].plot(t, ek[:, 0], "r", label="x")
        axes[1].plot(t, ek[:, 1], "b", label="y")
        axes[1].set_ylabel("K - xi [SLAM units/m]")
        axes[1].set_title(f"Fig. 2: scale error ({kin})")
        axes[1].set_xlabel("t [s]")
        axes[1].set_ylim(-0.35, 0.35)
        for ax in axes:
            ax.grid(True)
            ax.legend()
        fig.tight_layout()
        path = args.out / f"seed000_errors_{kin}.png"
        fig.savefig(path, dpi=120)
        plt.close(fig)
        print(f"    plot: {path.resolve()}")

    noisy = simulate("circle", args.seed, SimOptions(images=False))
    print("circle, noisy sensors (simulator defaults): steady state t > 20 s")
    for kin, gk in (("published", 8.0), ("full", 8.0), ("full", 1.0)):
        t, ev, ek, K = errors(
            noisy, IIObserverOptions(kinematics=kin, drag_k=drag, gamma_k=(gk, gk))
        )
        late = t > STEADY_T
        v_rmse = np.sqrt(np.mean(np.sum(ev[late] ** 2, axis=1)))
        rel = ek[late] / K[late]
        print(
            f"  {kin:9s} gamma_k={gk:g}: velocity RMSE {v_rmse:.3f} m/s, scale error mean "
            f"{np.round(100 * rel.mean(axis=0), 2)} %, RMS "
            f"{np.round(100 * np.sqrt(np.mean(rel**2, axis=0)), 2)} %"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
