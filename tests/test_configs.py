"""Every experiment config composes, validates and builds its components; a bad setting is
rejected with one line naming its key: by Hydra (unknown keys and options), by the checks of the
constructors the config names (ferl/config/validate.py: types, ranges, cross-key rules), or by the
trainer's setup (what involves two components)."""

import pytest
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.errors import HydraException
from hydra.utils import instantiate
from omegaconf import OmegaConf

from conftest import EXPERIMENTS, ROOT, run_train
from ferl.config.hydra_glue import condense_hydra_error
from ferl.config.params import ConfigError, check_node
from ferl.config.swaps import settings_read
from ferl.config.validate import validate
from ferl.data import DataError
from ferl.trainers.job import Job, SeedOffsets


def test_contract_experiments_exist():
    assert {
        "ch3_floor",
        "ch3_coding_cw",
        "ch3_coding_ccw",
        "ch3_coding_noreward",
        "table4_1_regular",
        "table4_1_matching",
        "table4_2_digit",
        "table5_1_bit",
        "table5_1_pixel",
        "passive_tmaze",
    } <= set(EXPERIMENTS)


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_experiment_composes_validates_and_builds(compose_cfg, name):
    cfg = compose_cfg([f"experiment={name}", "n_runs=2"])
    HydraConfig.instance().set_config(cfg)
    assert cfg.name == (name if name != "none" else "digit_floor")  # none: the groups' defaults, named by the env
    validate(cfg)
    # built as its trainer builds it: every component checked against its protocol (ferl/trainers/facts.py)
    trainer = instantiate(cfg.trainer)
    job = Job(cfg, torch.device("cpu"), SeedOffsets(), trainer.control, trainer.environment)
    # the actor's state: the (processed) observation, as the preprocessor reports it, and every predictor's memory
    n_obs = job.preprocessor.output_size if cfg.get("preprocessor") else job.env.observation_size
    n_state = n_obs + sum(p.n_memory for p in (cfg.get("predictor") or {}).values())
    assert job.actor.state_weights().shape == (2, n_state, cfg.actor.n_hidden)
    for p_cfg, predictor in zip((cfg.get("predictor") or {}).values(), job.predictors.values()):
        assert predictor.memory_size == p_cfg.n_memory
        if predictor.reward_output == "bits":  # one reward bit per reward value, read off the environment
            # the passive maze: its penalty and goal reward (0 is no bit); the others ±5, −1, −0.1
            assert predictor.W_rm.shape[1] == len(job.env.reward_values) == (2 if cfg.env.get("passive") else 4)
    optimal = job.env.optimal(cfg.actor.gamma)
    if job.env.task == "tmaze" and cfg.env.get("passive"):  # L steps of reward 0, then the goal
        assert optimal["discounted_return"] == pytest.approx(
            cfg.actor.gamma**cfg.env.corridor_length * cfg.env.goal_reward
        )
    elif job.env.task == "tmaze":
        assert optimal["discounted_return"] == pytest.approx(4.3175)
    elif job.env.task == "gymnasium":  # an outside task's optimum only where its config states one
        assert optimal == ({} if cfg.env.optimal_return is None else {"return": cfg.env.optimal_return})
    elif job.env.task == "digit_floor":
        assert optimal["reward_per_step"] == pytest.approx({"none": 0.0}.get(cfg.env.reward_condition, 8.0))
    else:  # the large-action task: every action bit right
        assert optimal["reward_per_step"] == cfg.env.action_bits
    trainer = instantiate(cfg.trainer)
    assert hasattr(trainer, "setup") and hasattr(trainer, "fit")


def test_every_option_file_is_its_constructors_signature():
    """Each option file of a component group names a constructor that takes every key it sets,
    with the type and range the constructor declares (one place per parameter)."""
    files = [p for p in (ROOT / "conf").glob("*/*.yaml") if p.parent.name not in ("experiment", "hparams_search")]
    assert len(files) >= 12
    for path in files:
        if path.parent.name == "trainer":
            continue  # phases that read the trainer's settings: composed below
        own = OmegaConf.load(path)
        # an option that extends another of its group (trainer/algorithm2_pixel → algorithm1)
        bases = [OmegaConf.load(path.parent / f"{d}.yaml") for d in own.get("defaults", []) if d != "_self_"]
        node = OmegaConf.to_container(OmegaConf.merge(*bases, own), resolve=False)
        node.pop("defaults", None)
        for name, part in node.items() if "_target_" not in node else [(path.stem, node)]:
            if path.parent.name == "data" and any(v == "???" or "${" in str(v) for v in part.values()):
                continue  # mnist_idx: data.root is the user's; mnist_full: the environment's ($FERL_MNIST_DIR)
            if path.read_text().startswith("# @package _global_") and "_target_" not in part:
                assert name in ("env",), f"{path}: a global option may set keys of the env only"
                continue  # actor/oracle's env.true_state: a key of another group's constructor
            check_node(part, f"{path.parent.name}.")


@pytest.mark.parametrize("name", sorted(p.stem for p in (ROOT / "conf" / "trainer").glob("*.yaml")))
def test_every_trainer_is_phases_and_a_run_node(compose_cfg, name):
    """Each trainer option is the phased trainer: its phases (each a target with its own keys), the
    run node every trainer shares, and settings that users override, each read by a phase or the
    run node: nothing else, and no setting that nothing reads."""
    cfg = compose_cfg(["experiment=none", f"trainer={name}"])
    node = cfg.trainer
    assert node._target_ == "ferl.trainers.phased.PhasedTrainer"
    assert node.run._target_ == "ferl.trainers.phased.RunControl" and node.phases
    fixed = {"_target_", "phases", "run", "kind", "environment", "seed_offsets"}
    assert settings_read(node, "trainer") == set(node) - fixed
    check_node(OmegaConf.to_container(node, resolve=True), "trainer.")  # every phase against its target


def test_a_setting_that_no_phase_reads_is_refused(compose_cfg):
    cfg = compose_cfg(["experiment=table4_1_matching", "+trainer.n_episode=5"])
    HydraConfig.instance().set_config(cfg)
    with pytest.raises(
        ConfigError,
        match=r"^trainer.n_episode is not allowed: no phase reads it; trainer takes "
        r"actor_obs_scale, checkpoint_every, collect_batch, ",
    ):
        validate(cfg)


def test_table_4_1_and_4_2_parameters(compose_cfg):
    cfg = compose_cfg(["experiment=table4_1_matching"])
    assert (cfg.env.corridor_length, cfg.env.max_steps, cfg.env.matching) == (3, 10, True)
    p, a, t = cfg.predictor.joint, cfg.actor, cfg.trainer
    assert (p.n_memory, p.rho_y, p.rho_r, p.c_y, p.c_a, p.beta_m, p.beta_y, p.lr) == (20, 1, 4, 1, 1, 1, 1, 0.05)
    assert "n_reward" not in p  # N^r = 4, one bit per reward value: the environment's (ferl/trainers/facts.py)
    assert (a.n_hidden, a.lr.value, a.beta.start, a.beta.end, a.gamma) == (20, 0.05, 0, 10, 0.95)
    assert (t.n_sample, t.l_training, t.n_epoch, t.n_episodes) == (2000, 5, 400, 10000)
    digit = compose_cfg(["experiment=table4_2_digit"])
    assert (digit.predictor.joint.rho_r, digit.env.matching, digit.actor.lr.value) == (4, True, 0.05)
    # the documented departures from Table 4.2 (conf/experiment/table4_2_digit.yaml)
    assert digit.predictor.joint.c_y == 0.1 and digit.predictor.joint.rho_y == pytest.approx(7 / 784, abs=1e-4)
    assert digit.trainer.actor_obs_scale == 0.1 and cfg.trainer.actor_obs_scale == 1


def test_table_5_1_parameters(compose_cfg):
    """Table 5.1: separate predictors with 20 memory nodes each, no ρ / c / gains; N_epoch 400 / 600;
    §5.3.2: RBM 784 → 20 by CD-3 for 600 sweeps, reservoirs of 100 images."""
    for name, epochs in (("table5_1_bit", 400), ("table5_1_pixel", 600)):
        cfg = compose_cfg([f"experiment={name}"])
        obs, rew = cfg.predictor.observation, cfg.predictor.reward
        assert list(cfg.predictor) == ["observation", "reward"]
        assert (obs.n_memory, obs.reward_output, obs.lr) == (20, "none", 0.05)
        assert (rew.n_memory, rew.reward_output, rew.predict_obs, rew.lr) == (20, "linear", False, 0.05)
        assert not {"rho_y", "rho_r", "c_y", "c_a", "beta_m", "beta_y"} & (set(obs) | set(rew))
        assert cfg.trainer.n_epoch == epochs and cfg.env.matching and cfg.actor.n_hidden == 20
    pixel = compose_cfg(["experiment=table5_1_pixel"])
    p = pixel.preprocessor
    assert (p.n_hidden, p.cd_k, p.sweeps) == (20, 3, 600)
    assert "n_visible" not in p  # 784 pixels: the environment's observation size (ferl/trainers/facts.py)
    assert pixel.env.reservoir_size == 100 and pixel.env.binarize_threshold is None
    assert len(set(pixel.env.digit_classes.values())) == 5  # Fig. 5.15: five digits
    assert compose_cfg(["experiment=table5_1_bit"]).trainer.n_sample == 2000
    assert pixel.trainer.n_sample == 8000  # the documented deviations (conf/experiment/table5_1_pixel.yaml)
    assert pixel.actor.lr_norm == "edges" and compose_cfg(["experiment=table5_1_bit"]).actor.lr_norm == "fan_in"
    assert compose_cfg(["experiment=table5_1_bit"]).get("preprocessor") is None


def test_dissertation_parameters(compose_cfg):
    """§3.5: α 0.1 → 0.01 exponentially, divided by √edges; β 0 → 2 linearly; γ = 0.9."""
    cfg = compose_cfg(["experiment=ch3_floor"])
    actor = instantiate(cfg.actor, n_runs=1, n_state=784, n_actions=4, seed=0)
    edges = (784 + 4) * 20
    assert actor.learning_rate(0.0) == pytest.approx(0.1 / edges**0.5)
    assert actor.learning_rate(1.0) == pytest.approx(0.01 / edges**0.5)
    assert actor.learning_rate(0.5) == pytest.approx((0.1 * 0.01) ** 0.5 / edges**0.5)
    assert actor.inverse_temperature(0.0) == 0 and actor.inverse_temperature(1.0) == 2
    assert actor.inverse_temperature(0.25) == pytest.approx(0.5)
    assert cfg.actor.gamma == 0.9 and cfg.trainer.steps == 100_000 and cfg.n_runs == 10


def config_error(compose_cfg, overrides) -> tuple[str, str]:
    """What train.py does before any work — compose, validate, build the trainer and set it up —
    up to the step that rejects the config: ("compose" | "validate" | "setup", the one-line
    message), or ("", "") when every step accepts it."""
    try:
        cfg = compose_cfg(overrides)
    except HydraException as e:  # what train.py's one_line_errors prints, without "ferl: error: "
        return "compose", condense_hydra_error(str(e) + (f"\n{e.__cause__}" if e.__cause__ else ""))
    HydraConfig.instance().set_config(cfg)
    try:
        validate(cfg)
    except ConfigError as e:
        return "validate", str(e)
    try:
        instantiate(cfg.trainer).setup(cfg, torch.device("cpu"))
    except (ConfigError, DataError) as e:  # train.py reports both alike
        return "setup", str(e)
    return "", ""


# a key that no config has, or a group option that does not exist: rejected while Hydra composes
COMPOSE_ERRORS = [
    ("actor.foo=1", "actor.foo"),
    ("task=maze", "task"),
    ("experiment=nope", "experiment"),
    ("experiment=table5_1_bit predictor.observation.rho_y=2", "predictor.observation.rho_y"),
]

# a value of the wrong type or outside a set of values: rejected by the constructor's annotations
TYPE_ERRORS = [
    ("env.noise=abc", "env.noise"),
    ("n_runs=2.5", "n_runs"),
    ("env.patches=x", "env.patches"),
    ("actor.td_rule=td_lambda", "actor.td_rule"),
    ("actor.lr_norm=sqrt", "actor.lr_norm"),
    ("env.reward_condition=up", "env.reward_condition"),
    ("device=tpu", "device"),
    ("seed=first", "seed"),
    ("resume=maybe", "resume"),
    ("compile=maybe", "compile"),
    ("actor.gamma=high", "actor.gamma"),
    ("actor.action_code=gray", "actor.action_code"),
    ("actor.action_selection=argmax", "actor.action_selection"),
    ("actor=recurrent_q predictor=none actor.head=rbm", "actor.head"),
    ("actor=recurrent_q predictor=none actor.memory=ntm", "actor.memory"),
    ("+actor.foo=1", "actor.foo"),
    ("trainer.test_noise_levels=[a]", "trainer.test_noise_levels"),
    ("data.test_per_class=many", "data.test_per_class"),
    ("experiment=table4_1_matching env.matching=perhaps", "env.matching"),
    ("experiment=table4_1_matching predictor.joint.time_average=maybe", "predictor.joint.time_average"),
    ("experiment=table4_1_matching predictor.joint.n_memory=2.5", "predictor.joint.n_memory"),
    ("experiment=table4_1_matching trainer.n_episodes=lots", "trainer.n_episodes"),
    ("experiment=table4_2_digit env.digit_classes.start_0=one", "env.digit_classes.start_0"),
    ("experiment=table5_1_bit predictor.reward.reward_output=gaussian", "predictor.reward.reward_output"),
    ("experiment=table5_1_bit +predictor.observation.n_memorys=2", "predictor.observation.n_memorys"),
    ("experiment=table5_1_pixel preprocessor.visible=gaussian", "preprocessor.visible"),
    ("experiment=table5_1_pixel preprocessor.persistent=maybe", "preprocessor.persistent"),
]

# a value of the right type that cannot work: rejected by the constructor's ranges and cross-key rules
VALUE_ERRORS = [
    ("env.noise=1.5", "env.noise"),
    ("env.noise=-0.1", "env.noise"),
    ("actor.n_hidden=0", "actor.n_hidden"),
    ("actor.n_hidden=-3", "actor.n_hidden"),
    ("n_runs=0", "n_runs"),
    ("trainer.steps=0", "trainer.steps"),
    ("actor.gamma=1.0", "actor.gamma"),
    ("env.noise_tile='4'", "env.noise_tile"),
    ("env.patches=0", "env.patches"),
    ("data=mnist_idx", "data.root"),
    ("data=mnist_idx data.root=/nonexistent", "data.root"),
    ("experiment=table4_1_regular env.corridor_length=0", "env.corridor_length"),
    ("experiment=table4_1_regular env.corridor_length=5 env.max_steps=4", "env.max_steps"),
    ("experiment=table4_1_regular env.max_steps=null", "env.max_steps"),
    ("experiment=passive_tmaze env.matching=true", "env.matching"),
    ("experiment=passive_tmaze env.max_steps=10", "env.max_steps"),
    ("experiment=table4_2_digit env.digit_classes.start_0=11", "env.digit_classes"),
    ("experiment=table4_2_digit +env.digit_classes.elsewhere=3", "env.digit_classes.elsewhere"),
    ("experiment=table4_2_digit ~env.digit_classes.corridor", "env.digit_classes.corridor"),
    ("experiment=table4_1_matching predictor.joint.n_memory=0", "predictor.joint.n_memory"),
    ("experiment=table4_1_matching trainer.train_fraction=1.0", "trainer.train_fraction"),
    (
        "experiment=table4_1_matching trainer.phases.predictors.checkpoint_every_epochs=0",
        "trainer.phases.predictors.checkpoint_every_epochs",
    ),
    ("experiment=table4_2_digit trainer.actor_obs_scale=0", "trainer.actor_obs_scale"),
    ("experiment=table5_1_pixel preprocessor.cd_k=0", "preprocessor.cd_k"),
    ("experiment=table5_1_pixel preprocessor.n_hidden=0", "preprocessor.n_hidden"),
    ("experiment=table4_1_matching actor.lr.value=-0.1", "actor.lr"),
    ("experiment=table5_1_bit predictor.reward.reward_output=none", "predictor.reward.reward_output"),
    ("experiment=table5_1_pixel env.reservoir_size=0", "env.reservoir_size"),
    ("experiment=table5_1_pixel env.binarize_threshold=2", "env.binarize_threshold"),
    ("experiment=table4_1_matching actor.bias_init_std=-1", "actor.bias_init_std"),
    ("trainer.prefetch=-1", "trainer.prefetch"),
    ("actor=recurrent_q predictor=none actor.context=30", "actor.context"),  # a transformer's key on a GRU
    ("actor=recurrent_q predictor=none actor.memory=transformer actor.heads=3", "actor.heads"),
]

# what involves two components: rejected by the trainer's setup, once they are built
SETUP_ERRORS = [
    # a size stated against the environment's own (ferl/trainers/facts.py)
    ("experiment=table5_1_pixel +preprocessor.n_visible=700", "preprocessor.n_visible=700 disagrees"),
    ("experiment=table4_1_matching +predictor.joint.n_reward=3", "predictor.joint.n_reward=3 disagrees"),
    ("experiment=table5_1_bit preprocessor=rbm", "preprocessor"),
    ("trainer.test_per_class=450", "trainer.test_per_class"),
    ("optimized_metric=final_discounted_return", "optimized_metric"),
    ("experiment=table5_1_pixel env.reservoir_size=101", "env.reservoir_size"),
    ("data.test_per_class=500", "data.test_per_class"),  # the embedded data hold 500 images a class
    (
        "experiment=passive_tmaze actor=recurrent_q predictor=none actor.memory=transformer actor.context=5",
        "actor.context",
    ),
]


@pytest.mark.parametrize("override,key", COMPOSE_ERRORS + TYPE_ERRORS + VALUE_ERRORS + SETUP_ERRORS)
def test_bad_values_name_their_key(compose_cfg, override, key):
    stage, message = config_error(compose_cfg, override.split())
    expected = {**{c: "compose" for c in COMPOSE_ERRORS}, **{c: "setup" for c in SETUP_ERRORS}}
    assert stage == expected.get((override, key), "validate"), message
    assert key in message and "\n" not in message, message
    if stage == "validate":
        assert message.startswith(f"{key}"), message  # the full key first, then the reason


def test_enum_errors_list_the_allowed_values(compose_cfg):
    from ferl.actors.softmax import TD_RULES

    _, message = config_error(compose_cfg, ["actor.td_rule=td_lambda"])
    assert all(rule in message for rule in TD_RULES), message


@pytest.mark.parametrize(
    "override",
    [
        "n_runs=2.5",
        "env.noise=abc",
        "actor.td_rule=td_lambda",
        "device=tpu",
        "actor.gamma=high",
        "trainer.steps=many",
        "experiment=table4_1_matching predictor.joint.time_average=maybe",
    ],
)
def test_type_errors_through_train_py(tmp_path, override):
    """A wrong type stops train.py before any work: one line naming the full key, no traceback,
    exit status ≠ 0, no run directory."""
    run_dir = tmp_path / "out" / "run"
    result = run_train(*override.split(), f"hydra.run.dir={run_dir}", timeout=120)
    assert result.returncode != 0
    lines = result.stderr.strip().splitlines()
    key = override.split()[-1].split("=")[0]
    assert len(lines) == 1 and lines[0].startswith(f"ferl: error: {key}"), result.stderr
    assert "Traceback" not in result.stderr + result.stdout
    assert not (tmp_path / "out").exists()
