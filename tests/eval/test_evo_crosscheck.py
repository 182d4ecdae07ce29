"""Our ATE and RPE equal evo's on TUM files of a seeded synthetic pair (evo is a test-only, GPL
dependency; fgnav never imports it)."""

from __future__ import annotations

import numpy as np
import pytest
from fgnav.datasets.geometry import matrix_to_quat_wxyz, rpy_to_matrix, so3_exp
from fgnav.datasets.tum import read_tum, write_tum
from fgnav.datasets.types import Trajectory

from fgnav.estimate import Estimate
from fgnav.eval.metrics import evaluate

evo_metrics = pytest.importorskip("evo.core.metrics")
evo_sync = pytest.importorskip("evo.core.sync")
evo_file = pytest.importorskip("evo.tools.file_interface")

RPE_DELTA_M = 5.0


def _noisy_offset_copy(truth: Trajectory, s: float, seed: int) -> Trajectory:
    """Truth with position/rotation noise, expressed in a world frame offset by a known Sim(3)."""
    rng = np.random.default_rng(seed)
    R = rpy_to_matrix(0.05, -0.1, 0.8)
    t = np.array([3.0, -1.0, 0.4])
    noisy_p = truth.world_t_body + rng.normal(0.0, 0.05, size=truth.world_t_body.shape)
    noisy_R = np.stack([Rb @ so3_exp(rng.normal(0.0, 0.01, 3)) for Rb in truth.world_R_body()])
    p = (noisy_p - t) @ R / s
    Rs = np.einsum("ji,njk->nik", R, noisy_R)
    return Trajectory(truth.t, p, matrix_to_quat_wxyz(Rs))


@pytest.mark.parametrize(("mode", "scale"), [("se3", 1.0), ("sim3", 0.3)])
def test_ate_and_rpe_equal_evo(truth, tmp_path, mode, scale):
    est = _noisy_offset_copy(truth, scale, seed=11)
    gt_path = write_tum(tmp_path / "truth.tum", truth)
    est_path = write_tum(tmp_path / "est.tum", est)

    ours = evaluate(Estimate("x", est), truth, alignment=mode, delta_m=RPE_DELTA_M)

    ref = evo_file.read_tum_trajectory_file(str(gt_path))
    traj = evo_file.read_tum_trajectory_file(str(est_path))
    ref, traj = evo_sync.associate_trajectories(ref, traj, max_diff=1e-3)
    assert traj.num_poses == len(truth)
    r, t, s = traj.align(ref, correct_scale=(mode == "sim3"))
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((ref, traj))
    stat = evo_metrics.StatisticsType
    assert ours.ate_rmse_m == pytest.approx(ape.get_statistic(stat.rmse), rel=1e-6)
    assert ours.ate_mean_m == pytest.approx(ape.get_statistic(stat.mean), rel=1e-6)
    assert ours.ate_max_m == pytest.approx(ape.get_statistic(stat.max), rel=1e-6)
    assert ours.align_scale == pytest.approx(s, rel=1e-9)
    # The noise is 5 cm per axis: ATE ~ 5 cm * sqrt(3).
    assert 0.07 < ours.ate_rmse_m < 0.11

    rpe = evo_metrics.RPE(
        evo_metrics.PoseRelation.translation_part,
        delta=RPE_DELTA_M,
        delta_unit=evo_metrics.Unit.meters,
        rel_delta_tol=0.1,
        all_pairs=True,
        pairs_from_reference=True,
    )
    rpe.process_data((ref, traj))
    assert ours.rpe_n_pairs == len(rpe.error)
    assert ours.rpe_rmse_m == pytest.approx(rpe.get_statistic(stat.rmse), rel=1e-6)


@pytest.mark.realdata
def test_ate_equals_evo_on_euroc_mh01(real_data):
    """rpg VIO estimate vs EuRoC MH_01 ground truth. evo pairs each estimate with the nearest
    truth sample (within 10 ms, truth at 200 Hz) while we interpolate the truth at the estimate's
    time, so the two agree to interpolation error, not to rounding: measured 0.204095 m (ours) vs
    0.204094 m (evo) after SE(3) alignment, 3,638 of 3,660 poses matched by both."""
    root = real_data / "euroc_MH_01_easy"
    gt_path = root / "groundtruth" / "MH_01_easy.txt"
    est_path = root / "rpg_vio_mono" / "stamped_traj_estimate.txt"
    ours = evaluate(Estimate("rpg_vio", read_tum(est_path)), read_tum(gt_path), alignment="se3")
    ref = evo_file.read_tum_trajectory_file(str(gt_path))
    traj = evo_file.read_tum_trajectory_file(str(est_path))
    ref, traj = evo_sync.associate_trajectories(ref, traj, max_diff=0.01)
    traj.align(ref)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((ref, traj))
    assert ours.n_matched == traj.num_poses == 3638
    assert ours.n_unmatched_before == 22
    assert ours.ate_rmse_m == pytest.approx(
        ape.get_statistic(evo_metrics.StatisticsType.rmse), rel=1e-4
    )
    assert ours.ate_rmse_m == pytest.approx(0.2041, abs=1e-3)
