"""TensorBoard logs of real runs, read back by ferl.runs and served by a real TensorBoard server.

One tiny digit-floor run and one tiny T-maze run go into a sweep-like folder (as Hydra's
multirun would lay them out); the server is started on that folder and queried through its
HTTP data API (the routes of tensorboard's scalars, hparams, images, histograms and projector
plugins)."""

import json
import socket
import subprocess
import sys
import time
import urllib.parse
import urllib.request

import numpy as np
import pytest

from conftest import ROOT, TINY, eager
from ferl import runs

TMAZE = [
    "experiment=table4_1_matching",
    "n_runs=2",
    "trainer.n_sample=200",
    "trainer.n_epoch=10",
    "trainer.n_episodes=300",
]
FLOOR_RUN, TMAZE_RUN = "0_ch3_coding_cw", "1_table4_1_matching"
PHASES = {"actor", "schedule", "test", "collect", "preprocessor", "hparam"}


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    """Both runs trained at the same time (two processes) into one folder."""
    root = tmp_path_factory.mktemp("sweep")
    jobs = [
        subprocess.Popen(
            [sys.executable, str(ROOT / "train.py"), *eager(args), f"hydra.run.dir={root / name}"],
            cwd=ROOT,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        for name, args in ((FLOOR_RUN, [*TINY, "experiment=ch3_coding_cw"]), (TMAZE_RUN, TMAZE))
    ]
    for job in jobs:
        _, err = job.communicate(timeout=300)
        assert job.returncode == 0, err[-2000:]
    return root


def summary(run_dir) -> dict:
    return json.loads((run_dir / "summary.json").read_text())


def test_runs_reads_back_config_metrics_and_scalars(sweep):
    r = runs.load(sweep)
    config = r.configs.set_index("run")
    assert list(config.index) == [FLOOR_RUN, TMAZE_RUN]
    assert config.loc[FLOOR_RUN, "name"] == "ch3_coding_cw"  # ${hydra:runtime.choices.experiment}, resolved
    assert config.loc[FLOOR_RUN, "trainer.test_noise_levels"] == (0.0, 0.125, 0.5)
    assert config.loc[FLOOR_RUN, "n_runs"] == 2 and config.loc[FLOOR_RUN, "actor.n_hidden"] == 20
    assert "trainer.steps=300" in config.loc[FLOOR_RUN, "overrides"]
    assert config.loc[TMAZE_RUN, "trainer.n_episodes"] == 300 and bool(config.loc[TMAZE_RUN, "env.matching"])

    m = r.metrics
    assert len(m) == 4 and list(m["seed"]) == [0, 1, 0, 1]
    floor, tmaze = (m[m["run"] == name] for name in (FLOOR_RUN, TMAZE_RUN))
    expected = summary(sweep / FLOOR_RUN)["metrics"]
    assert list(floor["greedy_accuracy/0.125"]) == expected["greedy_accuracy"]["0.125"]
    assert list(floor["reward_per_step_last10pct"]) == expected["reward_per_step_last10pct"]
    expected = summary(sweep / TMAZE_RUN)["metrics"]
    assert list(tmaze["final_discounted_return"]) == expected["final_discounted_return"]
    assert len(r.table()) == 4 and "actor.n_hidden" in r.table()

    s = r.scalars
    assert list(s.columns) == ["run", "run_dir", "tag", "step", "value", "wall_time"]
    for tag in s["tag"].unique():  # phase/quantity; hparam/<summary metric>, which may be per level
        phase, *rest = tag.split("/")
        assert (phase in PHASES or phase.startswith("predictor_")) and (len(rest) == 1 or phase == "hparam"), tag

    def series(run, tag):
        x = s[(s["run"] == run) & (s["tag"] == tag)]
        return list(x["step"]), x["value"].to_numpy()

    assert series(FLOOR_RUN, "actor/reward_ma100")[0] == [100, 200, 300]
    assert series(FLOOR_RUN, "schedule/beta")[0] == [100, 200, 300]
    assert series(FLOOR_RUN, "test/greedy_accuracy_0.125")[0] == [0, 300]  # before and after training
    np.testing.assert_allclose(
        series(FLOOR_RUN, "hparam/reward_per_step_last10pct")[1],
        [np.mean(floor["reward_per_step_last10pct"])],
        rtol=1e-6,
    )
    assert series(TMAZE_RUN, "actor/discounted_return_ma200")[0] == [100, 200, 300]
    assert series(TMAZE_RUN, "predictor_joint/error_test")[0] == list(range(1, 11))
    assert series(TMAZE_RUN, "collect/train_sequences")[0] == [0]
    np.testing.assert_allclose(
        series(TMAZE_RUN, "hparam/final_discounted_return")[1], [np.mean(tmaze["final_discounted_return"])], rtol=1e-6
    )

    one = runs.load(sweep / TMAZE_RUN, tags=r"^actor/")
    assert list(one.configs["run"]) == ["."] and set(one.scalars["tag"]) == {
        f"actor/{q}_ma200" for q in ("discounted_return", "steps", "terminal_reward", "td_abs_mean", "correct_goal")
    }


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


class TensorBoard:
    def __init__(self, port: int):
        self.base = f"http://127.0.0.1:{port}"

    def get(self, route: str, raw: bool = False, **query):
        url = f"{self.base}{route}" + (f"?{urllib.parse.urlencode(query)}" if query else "")
        with urllib.request.urlopen(url, timeout=30) as response:
            body = response.read()
        return body if raw else json.loads(body)

    def post(self, route: str, payload: dict):
        request = urllib.request.Request(
            f"{self.base}{route}",
            data=json.dumps(payload).encode(),
            headers={"Content-Type": "application/json"},
            method="POST",
        )
        with urllib.request.urlopen(request, timeout=30) as response:
            return json.loads(response.read())


@pytest.fixture(scope="module")
def server(sweep):
    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "tensorboard.main", "--logdir", str(sweep), "--host", "127.0.0.1", "--port", str(port)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    tb = TensorBoard(port)
    try:
        deadline = time.time() + 90
        while True:  # ready once the server answers and has loaded both runs' scalars
            assert proc.poll() is None, proc.stderr.read()[-2000:]
            try:
                if {f"{FLOOR_RUN}/tb", f"{TMAZE_RUN}/tb"} <= set(tb.get("/data/plugin/scalars/tags")):
                    break
            except OSError:
                pass
            assert time.time() < deadline, "TensorBoard did not serve both runs within 90 s"
            time.sleep(0.25)
        yield tb
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def test_tensorboard_serves_scalars(server, sweep):
    tags = server.get("/data/plugin/scalars/tags")
    assert {"actor/reward_ma100", "schedule/beta", "test/greedy_accuracy_0.125"} <= set(tags[f"{FLOOR_RUN}/tb"])
    assert {"actor/discounted_return_ma200", "predictor_joint/error_test", "collect/train_sequences"} <= set(
        tags[f"{TMAZE_RUN}/tb"]
    )
    points = server.get("/data/plugin/scalars/scalars", run=f"{TMAZE_RUN}/tb", tag="actor/discounted_return_ma200")
    read_back = runs.scalars(sweep / TMAZE_RUN, tags=["actor/discounted_return_ma200"])
    assert [p[1] for p in points] == list(read_back["step"]) == [100, 200, 300]
    np.testing.assert_array_equal([p[2] for p in points], read_back["value"])


def test_tensorboard_serves_hparams_one_row_per_job(server, sweep):
    experiment = server.post("/data/plugin/hparams/experiment", {"experimentName": ""})
    hparams = {h["name"] for h in experiment["hparamInfos"]}
    # the union over both jobs' configs, lists included; not just the first job's keys
    assert {
        "name",
        "seed",
        "actor.n_hidden",
        "trainer.test_noise_levels",
        "trainer.n_episodes",
        "env.matching",
    } <= hparams
    metrics = {m["name"]["tag"] for m in experiment["metricInfos"]}
    assert {
        "hparam/reward_per_step_last10pct",
        "hparam/greedy_accuracy/0.125",
        "hparam/final_discounted_return",
        "hparam/solved",
        "hparam/agent_steps_per_s",
    } <= metrics
    groups = server.post(
        "/data/plugin/hparams/session_groups",
        {
            "experimentName": "",
            "allowedStatuses": ["STATUS_SUCCESS", "STATUS_UNKNOWN"],
            "colParams": [],
            "startIndex": 0,
            "sliceSize": 100,
        },
    )["sessionGroups"]
    rows = {g["sessions"][0]["name"]: g for g in groups}
    assert len(groups) == 2 and set(rows) == {f"{FLOOR_RUN}/tb", f"{TMAZE_RUN}/tb"}
    tmaze = rows[f"{TMAZE_RUN}/tb"]
    assert tmaze["hparams"]["name"] == "table4_1_matching" and tmaze["hparams"]["trainer.n_sample"] == 200
    assert rows[f"{FLOOR_RUN}/tb"]["hparams"]["trainer.test_noise_levels"] == "[0.0, 0.125, 0.5]"
    value = {m["name"]["tag"]: m["value"] for m in tmaze["metricValues"]}["hparam/final_discounted_return"]
    expected = np.mean(summary(sweep / TMAZE_RUN)["metrics"]["final_discounted_return"])
    assert value == pytest.approx(expected, rel=1e-6)


def test_tensorboard_serves_images_histograms_and_embeddings(server):
    images = server.get("/data/plugin/images/tags")
    assert {"actor/W_sh_images", "test/observations_clean", "test/observations_noisy"} <= set(images[f"{FLOOR_RUN}/tb"])
    assert {"env/observations", "actor/W_sh_matrix"} <= set(images[f"{TMAZE_RUN}/tb"])
    tiles = server.get("/data/plugin/images/images", run=f"{FLOOR_RUN}/tb", tag="actor/W_sh_images")
    assert [t["step"] for t in tiles] == [0, 300]  # before and after training
    png = server.get(f"/data/plugin/images/individualImage?{tiles[-1]['query']}", raw=True)
    assert png.startswith(b"\x89PNG")

    histograms = server.get("/data/plugin/histograms/tags")
    assert {"actor/weights/W_sh", "actor/weights/W_ah"} <= set(histograms[f"{FLOOR_RUN}/tb"])
    assert {"predictor_joint/weights/W_mm", "actor/weights/W_sh"} <= set(histograms[f"{TMAZE_RUN}/tb"])

    assert {f"{FLOOR_RUN}/tb", f"{TMAZE_RUN}/tb"} <= set(server.get("/data/plugin/projector/runs"))
    for run, tag, n_points, header in (
        (FLOOR_RUN, "actor/hidden_test_digits:00300", 9 * 8, "class\toptimal_action\tgreedy_action"),
        (TMAZE_RUN, "actor/hidden_at_probe:00300", None, "condition\tinitial_signal\tjunction_signal"),
    ):
        info = server.get("/data/plugin/projector/info", run=f"{run}/tb")
        assert tag in [e["tensorName"] for e in info["embeddings"]]
        rows = server.get("/data/plugin/projector/metadata", raw=True, run=f"{run}/tb", name=tag).decode().splitlines()
        assert rows[0].startswith(header) and len(rows) > 1 and (n_points is None or len(rows) == n_points + 1)


def test_resume_rolls_the_event_files_back_to_the_checkpoint(tmp_path):
    """Points logged (and flushed) after the last checkpoint, in the same event file and in a
    file a later attempt started, are gone after `RunDir.resume`; the ones before it stay."""
    from torch.utils.tensorboard import SummaryWriter

    from conftest import tb_scalars
    from ferl.run.directory import RunDir

    run = RunDir(tmp_path / "run")
    with SummaryWriter(run.tb) as writer:
        for step in range(3):
            writer.add_scalar("actor/x", float(step), step)
        run.save_checkpoint({"step": 3}, writer)
        for step in range(3, 6):  # logged and on disk, but after the checkpoint
            writer.add_scalar("actor/x", float(step), step)
    with SummaryWriter(run.tb, filename_suffix=".later") as writer:
        writer.add_scalar("actor/x", 99.0, 4)
    assert len(tb_scalars(run.path)["actor/x"]) == 7

    assert run.resume() == {"step": 3}
    assert tb_scalars(run.path)["actor/x"] == [(0, 0.0), (1, 1.0), (2, 2.0)]
    assert len(list(run.tb.glob("events.out.tfevents.*"))) == 1


def test_resume_without_a_checkpoint_starts_the_log_afresh(tmp_path):
    from torch.utils.tensorboard import SummaryWriter

    from ferl.run.directory import RunDir

    run = RunDir(tmp_path / "run")
    with SummaryWriter(run.tb) as writer:
        writer.add_scalar("actor/x", 1.0, 0)
    (run.tb / "analysis").mkdir()  # analyze.py's own log is not the run's
    assert run.resume() is None
    assert not list(run.tb.glob("events.out.tfevents.*")) and (run.tb / "analysis").is_dir()


def test_weights_beyond_tensorboards_buckets_are_left_out_of_the_histograms(tmp_path):
    """A run on its way to diverging (finite weights of 1e30, met on CartPole) ended its phase
    with TensorBoard's "The histogram is empty", before the phase's records were written."""
    import torch
    from torch.utils.tensorboard import SummaryWriter

    from ferl.run.tensorboard import log_weights

    module = torch.nn.Module()
    module.w = torch.nn.Parameter(torch.tensor([[[1e30, -1e30], [float("nan"), 2.0]]]))
    module.huge = torch.nn.Parameter(torch.full((1, 2, 2), 1e25))
    writer = SummaryWriter(tmp_path)
    log_weights(writer, "actor", module, 0)  # raised ValueError before
    writer.close()
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(tmp_path), size_guidance={"histograms": 0}).Reload()
    assert events.Tags()["histograms"] == ["actor/weights/w"]  # "huge": nothing left, no histogram
    (histogram,) = events.Histograms("actor/weights/w")
    assert histogram.histogram_value.num == 1 and histogram.histogram_value.sum == 2.0
