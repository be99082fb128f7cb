import json
import zipfile

import numpy as np
import pytest
import torch

from snds.cli import main
from snds.train import TrainConfig

from conftest import SHARED_DATA

FAST = ["--steps", "150", "--rollouts", "100", "--samples", "5000"]


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    out = tmp_path_factory.mktemp("run") / "sine"
    assert (
        main(["--quiet", "train", "--motion", "Sine", "--demos", "3", "--out", str(out), *FAST])
        == 0
    )
    return out


def test_train_writes_model_metrics_and_config(trained):
    names = {p.name for p in trained.iterdir()}
    assert {"model.json", "model.safetensors", "metrics.json", "loss.json"} <= names
    metrics = json.loads((trained / "metrics.json").read_text())
    for key in (
        "velocity_mse",
        "velocity_mse_paper",
        "dtw",
        "dtw_paper",
        "final_distance",
        "train_seconds",
        "frechet",
        "frechet_paper",
        "swept_area",
        "swept_area_paper",
    ):
        assert np.isfinite(metrics[key]), key
    stability = metrics["stability"]
    assert stability["rollouts"] == 100 and stability["samples_checked"] == 5000
    assert stability["decrease_violations"] == 0
    assert stability["converged_fraction"] == 1.0
    description = json.loads((trained / "model.json").read_text())
    assert description["train"]["steps"] == 150
    assert description["train"]["shape_weight"] == 0.0  # off for position models
    # the warped V and its training defaults, recorded as numbers
    assert description["policy"]["warp_layers"] == 4
    assert description["policy"]["warp_features"] == 32
    assert description["train"]["position_noise"] == 0.0015
    assert description["train"]["warp_weight"] == 0.001
    assert description["train"]["nominal_weight"] == 0.01
    # the default phase (snds.phase), recorded so that every command rebuilds it
    assert description["data"] == {"motion": "Sine", "demos": 3, "phase": {"codes": 3, "seed": 0}}
    assert description["policy"]["phase_dim"] == 3 and description["dim"] == 5


def test_evaluate_rewrites_the_same_metrics(trained):
    before = json.loads((trained / "metrics.json").read_text())
    assert (
        main(["--quiet", "evaluate", str(trained), "--rollouts", "100", "--samples", "5000"]) == 0
    )
    after = json.loads((trained / "metrics.json").read_text())
    assert after["velocity_mse"] == pytest.approx(before["velocity_mse"], rel=1e-9)
    assert after["dtw"] == pytest.approx(before["dtw"], rel=1e-9)


def test_plot_writes_pngs(trained, tmp_path):
    assert main(["--quiet", "plot", str(trained), "--out", str(tmp_path)]) == 0
    pngs = sorted(p.name for p in tmp_path.glob("*.png"))
    # A default model has a phase: the streamlines of a new start's field and the paths; V's
    # contours over the plane would hide the phase.
    assert pngs == ["loss.png", "paths.png", "rollout_lyapunov.png", "streamlines.png"]


def test_plot_of_a_model_without_a_phase_draws_v(tmp_path):
    fast = ["--steps", "30", "--rollouts", "10", "--samples", "200", "--phase-codes", "0"]
    out = tmp_path / "plain"
    assert (
        main(["--quiet", "train", "--motion", "Sine", "--demos", "2", "--out", str(out), *fast])
        == 0
    )
    assert "phase" not in json.loads((out / "model.json").read_text())["data"]
    assert main(["--quiet", "plot", str(out), "--out", str(tmp_path / "plots")]) == 0
    pngs = sorted(p.name for p in (tmp_path / "plots").glob("*.png"))
    assert pngs == ["loss.png", "lyapunov.png", "rollout_lyapunov.png", "streamlines.png"]


@pytest.mark.parametrize(
    "argv, message",
    [
        (["train", "--motion", "Sinus"], "Sinus"),
        (["train", "--data", "missing.csv"], "missing.csv"),
        (["evaluate", "no_such_dir"], "no_such_dir"),
    ],
)
def test_bad_input_exits_2_with_one_line(argv, message, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["--quiet", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and message in err and "Traceback" not in err
    assert not any(tmp_path.iterdir())  # nothing half-written


def test_nan_in_csv_exits_2(tmp_path, capsys):
    path = tmp_path / "demos.csv"
    path.write_text("demo,t,x1,x2\n0,0,1,1\n0,1,nan,0.5\n0,2,0,0\n")
    assert main(["--quiet", "train", "--data", str(path), "--out", str(tmp_path / "m")]) == 2
    assert "demos.csv" in capsys.readouterr().err
    assert not (tmp_path / "m").exists()


def test_messy_snake_single_demo_end_to_end(tmp_path):
    path = SHARED_DATA / "Messy_snake.mat"
    if not path.exists():
        pytest.skip(f"{SHARED_DATA} is absent: the shared data folder is not beside the repo")
    out = tmp_path / "snake"
    assert (
        main(["--quiet", "train", "--data", str(path), "--demos", "1", "--out", str(out), *FAST])
        == 0
    )
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["stability"]["converged_fraction"] == 1.0
    assert metrics["stability"]["decrease_violations"] == 0


def test_chosen_demos_and_held_out_demos(tmp_path):
    out = tmp_path / "held_out"
    argv = ["--quiet", "train", "--motion", "Angle", "--demos", "0,2,4", "--test-demos", "1"]
    assert main([*argv, "--out", str(out), *FAST]) == 0
    description = json.loads((out / "model.json").read_text())
    assert description["data"]["demos"] == [0, 2, 4]
    assert description["split"]["test_demos"] == [1]
    before = json.loads((out / "metrics.json").read_text())
    assert main(["--quiet", "evaluate", str(out), "--rollouts", "100", "--samples", "5000"]) == 0
    after = json.loads((out / "metrics.json").read_text())
    assert after["velocity_mse"] == pytest.approx(before["velocity_mse"], rel=1e-9)


def test_malformed_demo_list_is_a_usage_error(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["train", "--motion", "Sine", "--demos", "1,x"])
    assert exit_info.value.code == 2
    assert "indices" in capsys.readouterr().err


def test_max_end_spread_merges_far_ends_and_is_recorded_for_evaluate(tmp_path, capsys):
    path = tmp_path / "far.csv"
    # Two demonstrations whose ends lie 1 apart: 45% of the extent from their mean.
    rows = ["demo,t,x1,x2"]
    for demo, end in enumerate((0.0, 1.0)):
        rows += [f"{demo},{t / 10},{1 - t / 10 + end * t / 10},{1 - t / 10}" for t in range(11)]
    path.write_text("\n".join(rows) + "\n")
    out = tmp_path / "merged"
    argv = ["--quiet", "train", "--data", str(path), "--out", str(out), *FAST]
    assert main(argv) == 2
    assert "--max-end-spread" in capsys.readouterr().err
    assert not out.exists()
    assert main([*argv, "--max-end-spread", "0.5"]) == 0
    assert json.loads((out / "model.json").read_text())["data"]["max_end_spread"] == 0.5
    # evaluate reloads the file with the recorded spread, not the default that refuses it.
    assert main(["--quiet", "evaluate", str(out), "--rollouts", "50", "--samples", "1000"]) == 0
    with pytest.raises(SystemExit) as exit_info:
        main([*argv, "--max-end-spread", "-1"])
    assert exit_info.value.code == 2
    assert "--max-end-spread: expected a number >= 0" in capsys.readouterr().err


def test_gaps_choose_how_a_mat_files_dropped_samples_are_read_and_are_recorded(tmp_path, capsys):
    import scipy.io

    from snds.data import DataSource

    # GIVEN two demonstrations along parabolas at 0.01 s, each missing 30 samples
    t = 0.01 * np.arange(120)
    keep = np.r_[0:40, 70:120]
    blocks = []
    for scale in (1.0, 1.2):
        positions = np.stack([scale * (1.2 - t) ** 2, scale * (1.2 - t)])
        velocities = np.stack([-2 * scale * (1.2 - t), -scale * np.ones_like(t)])
        blocks.append(np.concatenate([positions, velocities])[:, keep])
    path = tmp_path / "gaps.mat"
    scipy.io.savemat(path, {"Data": np.concatenate(blocks, axis=1), "dt": 0.01})
    samples = {}
    for gaps in (None, "retime"):
        out = tmp_path / f"model-{gaps}"
        argv = ["--quiet", "train", "--data", str(path), "--out", str(out), "--steps", "20"]
        argv += ["--rollouts", "20", "--samples", "500"]
        assert main(argv + (["--gaps", gaps] if gaps else [])) == 0
        record = json.loads((out / "model.json").read_text())["data"]
        samples[record["gaps"]] = sum(len(d.times) for d in DataSource.from_record(record).load())
    # THEN the default fills the gaps (30 samples back in each), retime keeps the 90 recorded
    assert samples == {"fill": 240, "retime": 180}
    # AND an unknown mode is refused by the parser
    with pytest.raises(SystemExit) as exit_info:
        main(["train", "--data", str(path), "--gaps", "drop"])
    assert exit_info.value.code == 2
    assert "--gaps: invalid choice" in capsys.readouterr().err


def test_relaxed_mode_turns_every_decay_term_off():
    from snds.cli import build_parser, policy_config
    from snds.data import Normalization, load_lasa
    from snds.policy import StablePolicy

    zeros = ["--decay-rate", "0", "--decay-far", "0", "--decay-near", "0"]
    args = build_parser().parse_args(["train", "--motion", "Sine", *zeros])
    config = policy_config(args)
    assert config.decay_rate == config.decay_far == config.decay_near == 0.0
    demos = load_lasa("Sine")
    policy = StablePolicy(dim=2, normalization=Normalization.fit(demos), config=config)
    x = torch.randn(1000, 2, dtype=torch.float64) * 5
    # a(x) = 0 far, near and in between: only dV/dt <= 0 is asked for.
    assert (policy.decay(torch.ones(1000, dtype=torch.float64), x) == 0).all()


def test_train_with_a_warped_v_end_to_end(tmp_path):
    out = tmp_path / "warped"
    argv = ["--quiet", "train", "--motion", "Sine", "--demos", "3", "--out", str(out), *FAST]
    assert main([*argv, "--warp-layers", "2", "--warp-weight", "0.01"]) == 0
    description = json.loads((out / "model.json").read_text())
    assert description["policy"]["warp_layers"] == 2
    assert description["train"]["warp_weight"] == 0.01
    stability = json.loads((out / "metrics.json").read_text())["stability"]
    assert stability["decrease_violations"] == 0 and stability["converged_fraction"] == 1.0
    from snds.models import load_model

    policy, _ = load_model(out)
    assert policy.lyapunov.warp is not None and len(policy.lyapunov.warp.layers) == 2


def test_metrics_report_arrival_retracing_and_warnings(trained):
    metrics = json.loads((trained / "metrics.json").read_text())
    stability = metrics["stability"]
    # times to arrive from the check's starts, in seconds and in the longest demo's durations
    assert 0 < stability["time_to_arrive_median"] <= stability["time_to_arrive_max"]
    assert stability["time_to_arrive_max"] <= stability["horizon"]
    assert stability["time_to_arrive_max_durations"] == pytest.approx(
        stability["time_to_arrive_max"] / stability["duration"]
    )
    assert stability["still_moving"] == stability["out_of_steps"] == 0
    # how far the rollouts from each demonstration's start stay from it (in extents): the
    # Frechet leash is at least the gap at the end
    assert metrics["retrace_durations"] == 1.5
    assert 0 < metrics["retrace_frechet_median"] <= metrics["retrace_frechet_max"]
    assert metrics["retrace_final_max"] <= metrics["retrace_frechet_max"]
    # a warning for a stiff field exactly when the safe step is below the data's
    stiff = stability["largest_safe_dt"] < stability["dt"]
    assert any(w.startswith("stiff field") for w in metrics["warnings"]) == stiff


def test_summary_line_gives_significant_digits_arrival_and_warnings(capsys):
    from snds.cli._common import summary

    # GIVEN the record of a well-fitted but stiff model that does not retrace
    stability = {
        "rollouts": 500,
        "converged_fraction": 1.0,
        "time_to_arrive_median": 2.345,
        "time_to_arrive_median_durations": 1.172,
        "time_to_arrive_max": 7.5,
        "time_to_arrive_max_durations": 3.75,
        "still_moving": 0,
        "horizon": 20.0,
        "decrease_violations": 0,
        "samples_checked": 50000,
        "integrator": "guarded euler",
        "largest_safe_dt": 3.3e-5,
        "dt": 0.01,
        "shortened_fraction": 0.99,
    }
    record = {
        "train_seconds": 9.04,
        "velocity_mse_paper": 4.2e-6,
        "dtw_paper": 0.0412,
        "retrace_frechet_max": 0.173,
        "retrace_frechet_median": 0.021,
        "stability": stability,
        "warnings": ["stiff field: ...", "rollouts ... do not retrace them: ..."],
    }
    line = summary(record)
    # THEN one line, numbers in significant digits (never "0.0000")
    assert "\n" not in line and "0.0000" not in line
    assert line == (
        "trained in 9.04 s; velocity MSE 4.2e-06 (paper scale), DTW 0.0412 (paper scale); "
        "from the demonstrations' starts Frechet 17.3 % of the extent at worst, 2.1 % median; "
        "arrived from 500 of 500 random starts in 2.35 s median (1.17x the longest "
        "demonstration), 7.5 s at most (3.75x); 0 decrease violations in 50000 samples; "
        "largest safe Euler step 3.3e-05 s (data: 0.01 s), guard shortened steps in 99 % of "
        "rollouts; WARNING: stiff field: ...; WARNING: rollouts ... do not retrace them: ..."
    )
    # and starts that did not arrive are counted as such, beside the cap
    short = summary({**record, "stability": {**stability, "converged_fraction": 0.072}})
    assert "arrived from 36 of 500 random starts" in short and "still moving at 20 s" in short


def test_evaluate_prints_the_summary_of_the_new_metrics(trained, capsys):
    args = ["evaluate", str(trained), "--rollouts", "100", "--samples", "5000"]
    assert main(args) == 0
    line = capsys.readouterr().out.strip()
    assert line.startswith(f"{trained}: trained in ") and line.count("\n") == 0
    assert "arrived from 100 of 100 random starts in " in line and "Frechet " in line


def test_a_zipped_model_is_refused_with_the_command_that_unzips_it(trained, tmp_path, capsys):
    # GIVEN the page's download: the model folder zipped as NAME/file
    archive = tmp_path / "model.zip"
    with zipfile.ZipFile(archive, "w") as zipped:
        for path in trained.iterdir():
            if path.is_file():
                zipped.write(path, f"snds-snds-1234/{path.name}")
    # THEN snds evaluate exits 2 with one line saying how to unzip it and what to pass
    assert main(["evaluate", str(archive)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (
        f"snds: error: {archive}: a zip archive, not a model folder; unzip it first: unzip "
        f"{archive} -d {tmp_path} and pass {tmp_path / 'snds-snds-1234'}"
    )


def test_plots_roll_out_until_every_rollout_arrives():
    # GIVEN pi = -0.2 x (slow: it arrives within 1 % of the extent after log(100) / 0.2 = 23 s)
    # and one demonstration of 4 s along a line: the plots used to stop at 1.5 x 4 s
    from snds.data import Demonstration, Demonstrations
    from snds.plotting import rollouts_until_arrival

    from conftest import linear_policy

    t = np.arange(0.0, 4.0 + 1e-9, 0.01)
    x = np.stack([1 - t / 4, 0 * t], axis=1)
    demos = Demonstrations(
        (Demonstration(positions=x, velocities=np.gradient(x, t, axis=0), times=t),), np.zeros(2)
    )
    starts = np.array([[1.0, 0.0], [0.0, -0.5]])
    rollouts, arrived = rollouts_until_arrival(linear_policy(0.2), demos, starts, dt=0.01)
    # THEN each is followed to the Euler step at which (1 - 0.002)^k |x0| <= 0.01 first holds,
    # in pieces of 6 s, and the longest run ends with the piece in which it arrives
    exact = np.ceil(np.log(0.01 / np.linalg.norm(starts, axis=1)) / np.log(1 - 0.002))
    np.testing.assert_array_equal(arrived, exact.astype(int))
    assert rollouts.shape[1] == 600 * int(np.ceil(exact.max() / 600)) + 1


def test_train_records_the_tracking_gain_and_smooth_weight_asked_for(tmp_path):
    out = tmp_path / "untracked"
    argv = ["--quiet", "train", "--motion", "Sine", "--demos", "2", "--out", str(out)]
    settings = ["--tracking-gain", "0", "--smooth-weight", "2e-5"]
    assert main([*argv, "--steps", "5", "--rollouts", "5", "--samples", "100", *settings]) == 0
    description = json.loads((out / "model.json").read_text())
    assert description["train"]["tracking_gain"] == 0.0
    assert description["train"]["smooth_weight"] == 2e-5
    assert description["train"]["tracking_share"] == TrainConfig().tracking_share
