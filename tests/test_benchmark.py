"""The benchmark sweep: names, resumability, and the same numbers locally and on Dask.

Every run here is the cheapest real one (Line, 30 steps, quick check), and the runs are
shared: the CLI trains Line/snds, the sweep fixture resumes from its folder and trains only
Line/bc, and the Dask cluster trains both again to compare.
"""

from __future__ import annotations

import csv
import json
import math
import shutil
import sys

import pytest

from snds import benchmark, stability
from snds.benchmark import MOTION_GROUPS, Task, resolve_methods, resolve_motions, run_sweep, sweep
from snds.cli import main
from snds.data import LASA_NAMES
from snds.errors import DataError, SNDSError
from snds.methods import METHODS
from snds.recipes import RECIPES

TINY = {"settings": benchmark.SweepSettings.quick(steps=30), "progress": False}
TASKS = benchmark.make_tasks(["Line"], ["snds", "bc"], seeds=1)


def test_groups_resolve_to_known_motions():
    assert resolve_motions("paper8") == list(MOTION_GROUPS["paper8"])
    assert len(MOTION_GROUPS["paper8"]) == 8
    assert resolve_motions("all") == list(LASA_NAMES)
    assert resolve_motions("multi") == [f"Multi_Models_{i}" for i in range(1, 5)]
    for group in MOTION_GROUPS.values():
        assert set(group) <= set(LASA_NAMES)


def test_names_and_groups_mix_without_duplicates():
    assert resolve_motions(" sine, Line ,paper8") == ["Sine", "Line"] + [
        m for m in MOTION_GROUPS["paper8"] if m != "Sine"
    ]


@pytest.mark.parametrize(
    ("spec", "named"),
    [("Sinus", "'Sinus'"), ("paper9", "'paper9'"), ("Line,nope", "'nope'"), (" , ", "no motions")],
)
def test_unknown_motion_is_named(spec, named):
    with pytest.raises(DataError, match=named):
        resolve_motions(spec)


def test_methods_registry_and_unknown_method():
    assert resolve_methods("snds,bc,snds") == ["snds", "bc"]
    assert METHODS["snds"].policy_config.stable and METHODS["snds"].has_lyapunov
    assert not METHODS["bc"].policy_config.stable and not METHODS["bc"].has_lyapunov
    with pytest.raises(SNDSError, match="'gmr'"):
        resolve_methods("snds,gmr")


def test_task_key_is_stable_and_round_trips_through_a_row():
    task = Task("Sine", "bc", 2, None)
    assert task.key == "Sine/bc/seed=2/demos=all"
    assert Task.from_row({"motion": "Sine", "method": "bc", "seed": 2, "demos": None}) == task
    assert Task("Sine", "bc", 2, 3).key != task.key


def test_cli_rejects_bad_names_with_exit_2(tmp_path, capsys):
    for bad in (["--methods", "snds,nope"], ["--motions", "Nope"]):
        code = main(["--quiet", "benchmark", *bad, "--out", str(tmp_path)])
        assert code == 2
        err = capsys.readouterr().err
        assert err.startswith("snds: error:") and "nope" in err.lower()
        assert err.count("\n") == 1


@pytest.fixture(scope="module")
def cli_run(tmp_path_factory):
    """`snds benchmark` end to end: one run of Line/snds."""
    out = tmp_path_factory.mktemp("cli")
    args = ["--motions", "Line", "--methods", "snds", "--seeds", "1", "--steps", "30"]
    assert main(["--quiet", "benchmark", *args, "--quick", "--jobs", "1", "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def local_sweep(cli_run, tmp_path_factory):
    """Line x (snds, bc) in-process, resumed from the CLI's folder; counts the runs."""
    out = tmp_path_factory.mktemp("sweep") / "local"
    shutil.copytree(cli_run, out)
    calls = []
    original = sweep.run_task

    def counting(task, settings):
        calls.append(task.key)
        return original(task, settings)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(sweep, "run_task", counting)
        rows = run_sweep(TASKS, out=out, jobs=1, **TINY)
    return out, rows, calls


def test_cli_writes_results_summary_and_figures(cli_run):
    names = {p.name for p in cli_run.iterdir()}
    figures = {"mse_violin.png", "dtw_violin.png", "train_time.png", "converged.png"}
    figures |= {"streamlines.png"}
    assert {"results.jsonl", "results.csv", "summary.md", "sweep.json", "models"} | figures <= names
    with open(cli_run / "results.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert [(r["motion"], r["method"], r["seed"]) for r in rows] == [("Line", "snds", "0")]
    assert int(rows[0]["samples_checked"]) == 5000
    assert int(rows[0]["decrease_violations"]) == 0
    # The interpreter with torch alone is well over 50 MiB; a whole machine's is far more.
    assert 50 < float(rows[0]["peak_memory_mb"]) < 8192


def test_sweep_keeps_each_run_model_loadable_with_its_numbers(cli_run):
    # GIVEN the model the sweep kept for Line/snds seed 0
    from snds.data import load_lasa, split_samples
    from snds.evaluate import accuracy
    from snds.models import load_model
    from snds.policy import float64_copy

    task = Task("Line", "snds", 0, None)
    policy, description = load_model(cli_run / task.model_dir)
    assert description["data"] == {"motion": "Line", "demos": None}
    assert description["train"]["steps"] == 30
    # THEN it reproduces the row's velocity MSE on the same split
    row = json.loads((cli_run / "results.jsonl").read_text().splitlines()[0])
    demos = load_lasa("Line")
    split = split_samples(demos, test_fraction=0.2, seed=0)
    mse = accuracy(float64_copy(policy), demos, split)["velocity_mse"]
    assert mse == pytest.approx(row["velocity_mse"], rel=1e-9)


@pytest.mark.parametrize(("method", "flags"), [("snds", []), ("bc", ["--unconstrained"])])
def test_a_sweep_trains_what_snds_train_trains(local_sweep, tmp_path, method, flags):
    # GIVEN the sweep's Line run of a network method (30 steps, seed 0, no phase)
    out, _, _ = local_sweep
    task = Task("Line", method, 0, None)
    # WHEN `snds train` trains the same data, steps and seed (a smaller check: it is not kept)
    args = ["--motion", "Line", "--steps", "30", "--phase-codes", "0", *flags]
    args += ["--rollouts", "5", "--samples", "100", "--out", str(tmp_path)]
    assert main(["--quiet", "train", *args]) == 0
    # THEN both went through the one run API: the same weights, bit for bit, and settings
    swept = out / task.model_dir
    assert (swept / "model.safetensors").read_bytes() == (
        tmp_path / "model.safetensors"
    ).read_bytes()
    ours, theirs = (json.loads((d / "model.json").read_text()) for d in (swept, tmp_path))
    assert ours["train"] == theirs["train"] and ours["split"] == theirs["split"]
    assert ours["policy"] == theirs["policy"] and ours["weights_sha256"] == theirs["weights_sha256"]


def test_cli_records_the_stability_check_size(tmp_path, monkeypatch):
    seen = []

    def fake(task, settings):
        seen.append(settings)
        raise SNDSError("stop here")

    monkeypatch.setattr(sweep, "run_task", fake)
    args = ["--motions", "Line", "--methods", "snds", "--seeds", "1", "--jobs", "1"]
    code = main(["--quiet", "benchmark", *args, "--rollouts", "7", "--out", str(tmp_path)])
    assert code == 2
    # the decrease check keeps the library's default size
    assert seen == [benchmark.SweepSettings(rollouts=7, samples=stability.SAMPLES)]
    assert json.loads((tmp_path / "sweep.json").read_text())["rollouts"] == 7
    with pytest.raises(SNDSError, match="rollouts"):
        benchmark.SweepSettings(rollouts=0)


def test_sweep_writes_one_row_per_task_and_a_summary(local_sweep):
    out, rows, calls = local_sweep
    # The CLI's Line/snds row was already in the folder: only bc was trained.
    assert calls == ["Line/bc/seed=0/demos=all"]
    assert [Task.from_row(r) for r in rows] == TASKS
    with open(out / "results.csv") as handle:
        table = list(csv.DictReader(handle))
    assert len(table) == 2 and list(table[0]) == list(benchmark.ROW_FIELDS)
    summary = (out / "summary.md").read_text()
    assert "| Line | snds | 1 |" in summary and "| Line | bc | 1 |" in summary
    assert "Total decrease violations: 0." in summary
    # The unconstrained policy has no V, so nothing was checked; the stable one has a V.
    by_method = {r["method"]: r for r in rows}
    assert by_method["bc"]["samples_checked"] == 0
    assert by_method["snds"]["samples_checked"] == 5000


def test_rerun_skips_finished_rows(local_sweep, monkeypatch):
    out, rows, _ = local_sweep
    before = (out / "results.jsonl").read_bytes()
    calls = []
    monkeypatch.setattr(sweep, "run_task", lambda task, settings: calls.append(task))
    again = run_sweep(TASKS, out=out, jobs=1, **TINY)
    assert calls == []
    assert (out / "results.jsonl").read_bytes() == before
    assert again == rows


def test_torn_last_line_is_dropped_and_rerun(local_sweep, tmp_path, monkeypatch):
    out, rows, _ = local_sweep
    shutil.copytree(out, tmp_path / "torn")
    results = tmp_path / "torn" / "results.jsonl"
    lines = results.read_text().splitlines()
    # A kill during the write of the second row leaves half of it and no newline.
    results.write_text(lines[0] + "\n" + lines[1][: len(lines[1]) // 2])
    redo = {json.loads(lines[1])["method"]: json.loads(lines[1])}
    calls = []

    def fake(task, settings):
        calls.append(task.key)
        return benchmark.TaskOutput(row=redo[task.method], model={"model.json": b"{}"})

    monkeypatch.setattr(sweep, "run_task", fake)
    again = run_sweep(TASKS, out=tmp_path / "torn", jobs=1, **TINY)
    assert len(calls) == 1 and again == rows
    assert [json.loads(line) for line in results.read_text().splitlines()] == [
        json.loads(lines[0]),
        json.loads(lines[1]),
    ]


def test_other_settings_in_the_same_folder_are_refused(local_sweep, monkeypatch):
    out, _, _ = local_sweep
    monkeypatch.setattr(sweep, "run_task", lambda task, settings: pytest.fail("ran"))
    with pytest.raises(SNDSError, match="another --out"):
        run_sweep(TASKS, out=out, jobs=1, settings=benchmark.SweepSettings.quick(steps=31))


def test_dask_cluster_gives_the_local_numbers(local_sweep, tmp_path):
    distributed = pytest.importorskip(
        "dask.distributed", reason="dask[distributed] not installed (pip install snds[cluster])"
    )
    _, local_rows, _ = local_sweep
    with distributed.LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=True,
        host="127.0.0.1",
        dashboard_address=None,
    ) as cluster:
        rows = run_sweep(TASKS, out=tmp_path, scheduler=cluster.scheduler_address, **TINY)
    assert [Task.from_row(r) for r in rows] == TASKS
    # One torch thread and a seed make training and evaluation deterministic: bit-equal.
    for local, remote in zip(local_rows, rows):
        for key in benchmark.ROW_FIELDS:
            if key in ("train_seconds", "train_cpu_seconds", "peak_memory_mb"):
                continue
            if isinstance(local[key], float):
                assert remote[key] == pytest.approx(local[key], rel=1e-9, nan_ok=True), key
            else:
                assert remote[key] == local[key], key


def test_scheduler_without_dask_says_how_to_install(tmp_path, monkeypatch):
    # None in sys.modules makes the import fail as if the package were absent.
    monkeypatch.setitem(sys.modules, "dask.distributed", None)
    monkeypatch.setattr(sweep, "run_task", lambda task, settings: pytest.fail("ran"))
    with pytest.raises(SNDSError, match=r"pip install snds\[cluster\]"):
        run_sweep(TASKS, out=tmp_path, scheduler="tcp://127.0.0.1:1", **TINY)


def test_summary_means_by_hand_and_rows_without_a_field():
    from snds.benchmark import summarise

    def row(seed, mse, cpu):
        return {
            "motion": "Sine",
            "method": "snds",
            "seed": seed,
            "velocity_mse_paper": mse,
            "dtw_paper": 1.0 + seed,
            "train_seconds": 10.0,
            "train_cpu_seconds": cpu,
            "converged_fraction": 1.0,
            "decrease_violations": 0,
            "shortened_fraction": 0.5,
        }

    line = summarise([row(0, 0.001, None), row(1, 0.003, None)]).splitlines()[2]
    # mean and (population) std over the two seeds, by hand: 0.002 ± 0.001, DTW 1.5 ± 0.5
    assert "| 0.002 ± 0.001 |" in line and "| 1.5 ± 0.5 |" in line
    # an older sweep's rows without CPU time say so, instead of nan
    assert "| n/a |" in line and "nan" not in line
    mixed = summarise([row(0, 0.001, 4.0), row(1, 0.003, None)]).splitlines()[2]
    assert "| 4.0 (1 runs) |" in mixed


def _rows(seeds: int) -> list[dict]:
    """Rows of a sweep of three methods on two motions (no models: no streamlines)."""
    rows = []
    for motion in ("Sine", "Angle"):
        for k, method in enumerate(("snds", "bc", "lpvds")):
            for seed in range(seeds):
                rows.append(
                    {
                        "motion": motion,
                        "method": method,
                        "seed": seed,
                        "velocity_mse_paper": 10.0 ** -(3 + k) * (1 + 0.1 * seed),
                        "dtw_paper": 0.5 + 0.2 * k + 0.01 * seed,
                        "train_seconds": 10.0 - 3 * k,
                        "train_cpu_seconds": 10.0,
                        # bars that reach the top of the axes, where a legend used to sit
                        "converged_fraction": 1.0 if method != "bc" else 0.1,
                        "decrease_violations": 0,
                        "shortened_fraction": 0.02,
                    }
                )
    return rows


def test_summary_of_one_seed_shows_values_without_spread_and_explains_its_columns():
    from snds.benchmark import PAPER_SNDS_MSE, summarise

    table = summarise(_rows(1))
    lines = table.splitlines()
    # THEN one run shows its value, never "± 0"
    assert "±" not in "\n".join(lines[2:8])
    # the paper's SNDS MSE is on the snds rows only
    snds, bc, lpvds = (line.split(" | ") for line in lines[2:5])
    assert snds[4] == str(PAPER_SNDS_MSE["Sine"]) and bc[4] == "-" and lpvds[4] == "-"
    # and the columns are explained under the table
    assert "Shortened: the fraction of those rollouts in which the guarded Euler step" in table
    assert "Converged: the fraction of the stability check's random starts" in table


def _overlaps(a, b) -> bool:
    return a.x0 < b.x1 and b.x0 < a.x1 and a.y0 < b.y1 and b.y0 < a.y1


@pytest.mark.parametrize("seeds", [1, 3])
def test_figure_legends_lie_inside_the_figure_and_cover_no_data(tmp_path, seeds):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.collections import PathCollection
    from matplotlib.patches import Rectangle

    from snds.benchmark import benchmark_figures

    # GIVEN the figures of a sweep of one seed (dots, no violins) or three
    figures = benchmark_figures(_rows(seeds))
    assert list(figures) == ["mse_violin.png", "dtw_violin.png", "train_time.png", "converged.png"]
    for path, fig in figures.items():
        renderer = FigureCanvasAgg(fig).get_renderer()
        fig.draw(renderer)
        whole = fig.bbox
        legends = fig.legends + [ax.get_legend() for ax in fig.axes if ax.get_legend()]
        assert len(legends) == 1, path
        box = legends[0].get_window_extent(renderer)
        # THEN the legend lies inside the figure, not cut at its sides
        assert whole.x0 <= box.x0 and box.x1 <= whole.x1, path
        assert whole.y0 <= box.y0 and box.y1 <= whole.y1, path
        # and covers no data: no dot, no bar, no axes' data area
        for ax in fig.axes:
            assert not _overlaps(box, ax.get_window_extent(renderer)), path
            for artist in ax.get_children():
                if isinstance(artist, PathCollection | Rectangle) and artist.get_visible():
                    if isinstance(artist, Rectangle) and artist is ax.patch:
                        continue
                    assert not _overlaps(box, artist.get_window_extent(renderer)), path


@pytest.fixture(scope="module")
def pose_sweep(tmp_path_factory):
    """`snds benchmark --se3` end to end: two demonstrations of Line lifted to SE(3), snds,
    one seed."""
    out = tmp_path_factory.mktemp("pose")
    args = ["--motions", "Line", "--se3", "--methods", "snds", "--seeds", "1", "--steps", "30"]
    args += ["--demos", "2", "--rollouts", "20", "--samples", "2000", "--jobs", "1"]
    assert main(["--quiet", "benchmark", *args, "--out", str(out)]) == 0
    return out


def test_pose_task_sweeps_end_to_end_and_resumes(pose_sweep, monkeypatch):
    from snds.data import split_samples
    from snds.evaluate import accuracy
    from snds.models import load_model
    from snds.policy import float64_copy
    from snds.spaces import SE3

    # GIVEN the row and the model of the pose sweep
    row = json.loads((pose_sweep / "results.jsonl").read_text().splitlines()[0])
    assert (row["motion"], row["se3"], row["samples_checked"]) == ("Line", True, 2000)
    assert row["decrease_violations"] == 0
    assert 0.0 <= row["final_angle_error"] <= math.pi and math.isfinite(row["angle_error_along"])
    task = Task("Line", "snds", 0, 2, se3=True)
    assert task.key == "Line/snds/seed=0/demos=2/se3" and Task.from_row(row) == task
    policy, description = load_model(pose_sweep / task.model_dir)
    assert isinstance(policy.space, SE3) and description["kind"] == "se3"
    assert description["data"] == {"motion": "Line", "demos": 2, "orientation_seed": 0}
    # The default recipe's training settings, as `snds train --se3` uses them for poses.
    default = RECIPES["default"].train
    assert description["train"]["shape_weight"] == default.shape_weight
    assert description["train"]["position_noise"] == default.position_noise
    # THEN the model reproduces the row's velocity MSE on the same split of the same poses
    demos = task.source().load()
    split = split_samples(demos, test_fraction=0.2, seed=0)
    mse = accuracy(float64_copy(policy), demos, split)["velocity_mse"]
    assert mse == pytest.approx(row["velocity_mse"], rel=1e-9)
    summary = (pose_sweep / "summary.md").read_text()
    assert "| Line-se3 | snds | 1 |" in summary and "final angle (rad)" in summary
    # AND a rerun trains nothing
    monkeypatch.setattr(sweep, "run_task", lambda *a: pytest.fail("retrained"))
    monkeypatch.setattr(sweep, "run_batch", lambda *a: pytest.fail("retrained"))
    settings = benchmark.SweepSettings(steps=30, rollouts=20, samples=2000)
    assert run_sweep([task], out=pose_sweep, jobs=1, settings=settings, progress=False) == [row]


def test_pose_tasks_refuse_position_only_methods(tmp_path, capsys):
    out = tmp_path / "out"
    code = main(
        ["--quiet", "benchmark", "--motions", "Line", "--se3", "--methods", "snds,lpvds"]
        + ["--out", str(out)]
    )
    assert code == 2
    err = capsys.readouterr().err
    assert "lpvds does not fit SE3 tasks (Line-se3)" in err and "snds, bc" in err
    assert not out.exists()


def test_a_pose_file_is_an_se3_task_and_a_missing_file_is_named(tmp_path):
    poses = tmp_path / "poses.csv"
    poses.write_text("demo,t,x,y,z,qx,qy,qz,qw\n")
    assert resolve_motions(f"Line,{poses}") == ["Line", str(poses)]
    task = Task(str(poses), "bc", 1)
    assert task.se3 and task.label == "poses-se3" and task.key.endswith("/se3")
    assert task.model_dir.parts[:2] == ("models", "poses-se3")
    with pytest.raises(DataError, match="nowhere.mat: no such demonstrations file"):
        resolve_motions(str(tmp_path / "nowhere.mat"))
