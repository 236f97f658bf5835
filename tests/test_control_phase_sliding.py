"""benchmarks/control_phase_sliding.py: the control of the default features does not carry the
gait cycle, Holden's (root smoothed 0.05 s) does."""

from __future__ import annotations

import glob

import pytest

from motionflows.data.features import ROOT_SIGMA_S


def test_real_poses_out_of_phase_with_their_control_slide_only_with_holdens_root(
    benchmark_script,
):
    module = benchmark_script("control_phase_sliding")
    files = sorted({f for g in module.DEFAULT_TAKES for f in glob.glob(g)})[::25]
    if not files:
        pytest.skip("needs ../shared/data (the Bandai takes)")
    holden = module.measure(files, 0.05, shifts=[5])
    ours = module.measure(files, ROOT_SIGMA_S, shifts=[5])
    # the ground truth on its own control is the same motion either way
    own = holden["own_control"]["foot_sliding_m_s"]
    assert ours["own_control"]["foot_sliding_m_s"] == pytest.approx(own, rel=1e-3)
    assert own < 0.1
    # half a step out of phase: Holden's control makes the planted feet slide, ours barely
    assert holden["control_shifted_5_frames"]["foot_sliding_m_s"] > 3 * own
    assert ours["control_shifted_5_frames"]["foot_sliding_m_s"] < 2 * own
    assert (
        ours["control_within_window_std"]["forward"]
        < 0.5 * holden["control_within_window_std"]["forward"]
    )


def test_no_takes_is_one_clear_error(benchmark_script, tmp_path, capsys):
    assert benchmark_script("control_phase_sliding").main(["--takes", str(tmp_path / "*.bvh")]) == 2
    assert "no BVH take matches" in capsys.readouterr().err
