"""Reproduce seed 004's scale-estimation experiment (Logachev & Minin; method of Engel et al.).

The paper flew 10 flights of each kind, took a displacement pair every second and re-estimated the
scale; it reports convergence to +-1.7 % after 2 s for vertical motion (pairs from the altimeter)
and to +-5 % after 15 s for a horizontal rectangle (pairs from the onboard velocity).

Here: simulated ``vertical`` and ``rectangle`` flights (seeds 0..N-1, noisy sensors, no images);
metric displacements from the rangefinder height (vertical, :func:`vertical_velocity_from_range`)
and from the integrated drag-model velocity of the I&I observer (horizontal: the accelerometer's
rotor-drag velocity stands in for the AR.Drone's onboard optical-flow velocity); SLAM displacements
rotated into world axes with the AHRS attitude. Prints the relative scale error (mean and standard
deviation over the flights) against time since the start of the SLAM session, and saves a plot.

Usage: ``python scripts/reproduce_seed004.py [--flights 10] [--out out/seed004]``
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from fgnav.datasets.geometry import interpolate_quat_wxyz
from fgnav.datasets.simulate import SimOptions, simulate

from fgnav.frontends.ii_observer import (
    IIObserverOptions,
    run_ii_observer,
    vertical_velocity_from_range,
)
from fgnav.frontends.scale_ml import (
    MLScaleOptions,
    PairOptions,
    estimate_scale,
    scale_pairs_from_flight,
)

#: Seed 004's reported figures: (time after start [s], +- relative error).
PAPER = {"vertical": (2.0, 0.017), "rectangle": (15.0, 0.05)}

#: Displacement noises per experiment. SLAM: simulator's 1 cm position noise at s ~ 1, twice
#: (two ends) -> ~0.015 SLAM units. Metric: rangefinder height after the vertical filter ~0.02 m;
#: drag-model velocity error ~0.1 m/s (accelerometer bias / k) integrated over 1 s -> 0.1 m.
SIGMAS = {"vertical": (0.015, 0.02), "rectangle": (0.015, 0.1)}


def run_one(scenario: str, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Relative scale error history ``(t since session start, error)`` of one flight."""
    flight = simulate(scenario, seed, SimOptions(images=False))
    truth = flight.meta["truth"]["slam_sessions"]["0"]
    s_true = truth["scale"]
    q_imu = interpolate_quat_wxyz(
        flight.attitude.t, flight.attitude.world_q_body_wxyz, flight.imu.t
    )
    q_slam = interpolate_quat_wxyz(
        flight.attitude.t, flight.attitude.world_q_body_wxyz, flight.slam.t
    )
    if scenario == "vertical":
        vv = vertical_velocity_from_range(flight, q_imu)
        pairs = scale_pairs_from_flight(
            flight, q_slam, height=(vv.t, vv.height), options=PairOptions(components="vertical")
        )
    else:
        obs = run_ii_observer(
            flight,
            IIObserverOptions(kinematics="full", drag_k=tuple(truth_drag(flight))),
            world_q_body_wxyz=q_imu,
        )
        pairs = scale_pairs_from_flight(
            flight,
            q_slam,
            world_velocity=(obs.t, obs.world_v_body),
            options=PairOptions(components="horizontal"),
        )
    sx, sy = SIGMAS[scenario]
    res = estimate_scale(pairs, MLScaleOptions(sigma_slam=sx, sigma_metric=sy))
    hist = res.history[0]
    # The simulator's scale drifts slowly within a session: compare with s(t).
    s_t = s_true * (1.0 + truth["scale_drift_per_s"] * (hist[:, 0] - truth["t_start"]))
    return hist[:, 0] - flight.slam.t[0], hist[:, 1] / s_t - 1.0


def truth_drag(flight) -> list[float]:
    """The drag coefficient mu/m: the paper's observers take it as a known calibration."""
    return list(flight.meta["truth"]["drag_k"])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--flights", type=int, default=10, help="flights per experiment (paper: 10)")
    ap.add_argument("--out", type=Path, default=Path("out/seed004"))
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    grid = np.arange(1.0, 31.0)
    curves = {}
    for scenario in ("vertical", "rectangle"):
        errs = []
        for seed in range(args.flights):
            t, e = run_one(scenario, seed)
            # Error at each grid time: the latest estimate available then (NaN before the first).
            k = np.searchsorted(t, grid + 1e-9, side="right") - 1
            errs.append(np.where(k >= 0, e[np.clip(k, 0, None)], np.nan))
        errs = np.asarray(errs)
        curves[scenario] = errs
        t_paper, tol = PAPER[scenario]
        print(
            f"\n{scenario}: relative scale error over {args.flights} flights (mean +- std, |max|)"
        )
        for g in (1, 2, 3, 5, 10, 15, 20, 30):
            col = errs[:, int(g) - 1]
            col = col[np.isfinite(col)]
            if col.size:
                print(
                    f"  t={g:4.0f} s  {100 * col.mean():+6.2f} % +- {100 * col.std():5.2f} %"
                    f"  |max| {100 * np.abs(col).max():5.2f} %"
                )
        col = errs[:, int(t_paper) - 1]
        col = col[np.isfinite(col)]
        print(
            f"  paper: +-{100 * tol:.1f} % after {t_paper:.0f} s; ours at {t_paper:.0f} s: "
            f"std {100 * col.std():.2f} %, RMS {100 * np.sqrt(np.mean(col**2)):.2f} %"
        )
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    for ax, (scenario, errs) in zip(axes, curves.items(), strict=True):
        have = np.any(np.isfinite(errs), axis=0)
        m, s = np.nanmean(errs[:, have], axis=0), np.nanstd(errs[:, have], axis=0)
        ax.plot(grid[have], 100 * m, "k-", label="mean")
        ax.fill_between(grid[have], 100 * (m - s), 100 * (m + s), color="0.8", label="+-1 std")
        t_paper, tol = PAPER[scenario]
        ax.errorbar([t_paper], [0.0], yerr=[100 * tol], fmt="ro", capsize=4, label="paper")
        ax.set_title(f"{scenario}: ML scale error")
        ax.set_xlabel("time since SLAM start [s]")
        ax.grid(True)
        ax.legend()
    axes[0].set_ylabel("relative scale error [%]")
    axes[0].set_ylim(-20, 20)
    path = args.out / "seed004_scale_error.png"
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"\nplot: {path.resolve()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
