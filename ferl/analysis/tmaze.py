"""One T-maze run (chapters 4–5) → its figures, data files and judged claims.

`TMazeRun` loads the T-maze records of docs/records.md plus `summary.json` and the
run's `.hydra/config.yaml`, and derives what the figures and claims share: the
prediction errors of each predictor (Eq. 4.8; Figs. 4.5/4.10, and 5.2/5.17 for the
observation and reward predictors of chapter 5), 200-episode moving averages of the
behaviour (Figs. 4.6–4.8, 4.11–4.13, 5.3–5.6, 5.18–5.19) and PCA projections of the
activations at the T-junction with the silhouette of the task conditions and, for
memories, of the initial signal on PC1–3 (Figs. 4.14–4.19, 5.7–5.13, 5.20–5.25).
A run is chapter 5 (Algorithm 2) when its predictors are not the single `joint` one of
Algorithm 1; its RBM preprocessor, where it has one, is analysed by
`ferl.analysis.preprocessor` (Figs. 5.15–5.16). `Numbering` maps every figure to the
dissertation's. `analyze` writes the numbers into the run's `analysis/` folder and
returns the figures and claims for the report.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np
import yaml

from ferl.analysis import preprocessor as preproc
from ferl.analysis import tmaze_figures as figs
from ferl.analysis.coding import moving_average, pca, sem_over_runs, subsampled_silhouette
from ferl.analysis.floor import _fmt, _load_npz, _write_csv
from ferl.analysis.report import TMAZE_CLAIMS, RunAnalysis, evaluate
from ferl.envs.tmaze import observation_names

TASK = "tmaze"
WINDOW = 200                  # moving-average window of Figs. 4.6–4.8, 4.11–4.13
PHASE_EPISODES = 1000         # "first / last 1000 episodes" of Figs. 4.14–4.19
N_PCS = 3                     # separation is scored on PC1–3, the space of Fig. 4.19(b)
L_TRAINING = 5                # Tables 4.1/4.2/5.1, for runs without trainer.l_training
GOAL_REWARD = 5.0             # terminal reward at the correct goal (§4.3.1)
MAX_SILHOUETTE_POINTS = 2000  # visits per run and phase; bounds the O(n²) distances
PHASES = ("first", "last")
FIGURE_RUN = 0                # the dissertation's junction figures show single runs
VISIT_KEYS = ("run", "episode", "step", "condition", "initial_signal", "junction_signal",
              "steps_to_goal")
CURVES = {  # episodes.npz key → (axis label, optimum: TMazeRun attribute, number or None)
    "discounted_return": ("discounted return", "optimal_return"),
    "steps": ("steps to the goal", "optimal_steps"),
    "terminal_reward": ("terminal reward", GOAL_REWARD),
    "correct_goal": ("correct-goal rate", 1.0),
    "td_abs_mean": ("mean |δ| per episode", None),
}
LABELLINGS = {"condition": "conditions", "initial_signal": "initial signal"}


# ---- numbers -----------------------------------------------------------------

def curve(values: np.ndarray, window: int = WINDOW) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(R, N) per-episode values → (episode, mean, s.e.m. over runs) of the trailing
    `window`-episode moving average; `episode` is the 1-based last episode of each window."""
    values = np.asarray(values, dtype=np.float64)
    window = min(window, values.shape[1])
    ma = moving_average(values, window)
    return np.arange(window, values.shape[1] + 1), ma.mean(axis=0), sem_over_runs(ma)


def nanmean(x: np.ndarray, axis=None) -> np.ndarray:
    """np.nanmean without the warning for cells that are NaN in every run (t > T)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmean(x, axis=axis)


@dataclass(frozen=True)
class LayerFigures:
    """Where the dissertation shows a junction layer: its activations, their PCA per phase with
    the explained variance, and the projection on PC1–3 (None: not shown, not drawn)."""
    activations: str
    pca: str
    pca3d: str | None = None


@dataclass(frozen=True)
class Numbering:
    """The dissertation's figures of one model (chapter 4: Algorithm 1, one `joint` predictor;
    chapter 5: Algorithm 2, `observation` and `reward` predictors) on one maze."""
    parameters: str                  # the table of parameters (L_training)
    prediction_errors: str
    predictor_panels: dict[str, str]  # predictor → its panel of the prediction-error figure
    learning_curves: str
    td_errors: str
    layers: dict[str, LayerFigures]  # junction layer → figures; "memory": any other memory

    def prediction_figure(self, name: str) -> str:
        return self.prediction_errors + self.predictor_panels.get(name, "")

    def layer(self, name: str) -> LayerFigures:
        return self.layers.get(name, self.layers["memory"])


CH4_LAYERS = {"memory": LayerFigures("Fig. 4.14(a)", "Fig. 4.14(b)"),
              "state": LayerFigures("Fig. 4.15(a)", "Figs. 4.15(b)/4.16"),
              "hidden": LayerFigures("Fig. 4.17(a)", "Figs. 4.17(b)/4.19(a)", "Fig. 4.19(b)")}
CH4_REGULAR = Numbering("Tables 4.1/4.2", "Fig. 4.5", {}, "Figs. 4.6–4.7", "Fig. 4.8", CH4_LAYERS)
CH4_MATCHING = Numbering("Tables 4.1/4.2", "Fig. 4.10", {}, "Figs. 4.11–4.12", "Fig. 4.13",
                         CH4_LAYERS)
CH5_PANELS = {"observation": "(a)", "reward": "(b)"}  # Figs. 5.2/5.17: (a) Eq. 5.1, (b) Eq. 5.2
CH5_BIT = Numbering("Table 5.1", "Fig. 5.2", CH5_PANELS, "Figs. 5.3–5.5", "Fig. 5.6", {
    "memory": LayerFigures("Figs. 5.7–5.8(a)", "Figs. 5.7–5.8(b)"),
    "memory_reward": LayerFigures("Fig. 5.7(a)", "Fig. 5.7(b)"),
    "memory_observation": LayerFigures("Fig. 5.8(a)", "Fig. 5.8(b)"),
    "state": LayerFigures("Fig. 5.9(a)", "Figs. 5.9(b)/5.10(a)", "Fig. 5.10(b)"),
    "hidden": LayerFigures("Figs. 5.11(a)/5.12", "Figs. 5.11(b)/5.13(a)", "Fig. 5.13(b)")})
CH5_DIGIT = Numbering("Table 5.1", "Fig. 5.17", CH5_PANELS, "Figs. 5.18–5.19(a–b)",
                      "Fig. 5.19(c–d)", {
    "memory": LayerFigures("Figs. 5.20–5.21(a)", "Figs. 5.20–5.21(b)"),
    "memory_reward": LayerFigures("Fig. 5.20(a)", "Fig. 5.20(b)"),
    "memory_observation": LayerFigures("Fig. 5.21(a)", "Fig. 5.21(b)"),
    "state": LayerFigures("Fig. 5.22(a)", "Figs. 5.22(b)/5.23(a)", "Fig. 5.23(b)"),
    "hidden": LayerFigures("Figs. 5.24(a)/5.25(a)", "Figs. 5.24(b)/5.25(b)")})


@dataclass(frozen=True)
class Projection:
    """PCA of one layer over the junction visits of one run in one phase."""
    visits: np.ndarray     # indices into the junction records
    scores: np.ndarray     # (n, N_PCS) coordinates on PC1–3
    explained: np.ndarray  # explained-variance ratio of every PC


# ---- one run ---------------------------------------------------------------------

@dataclass
class TMazeRun:
    run_dir: Path
    summary: dict
    predictor: dict[str, np.ndarray]
    episodes: dict[str, np.ndarray]
    junction: dict[str, np.ndarray]
    config: dict                                # .hydra/config.yaml; {} without one
    preprocessor: dict[str, np.ndarray] | None  # records/preprocessor.npz (Algorithm 2)

    @classmethod
    def load(cls, run_dir: Path) -> TMazeRun:
        records = run_dir / "records"
        config = run_dir / ".hydra" / "config.yaml"
        rbm = records / "preprocessor.npz"
        return cls(run_dir, json.loads((run_dir / "summary.json").read_text()),
                   _load_npz(records / "predictor.npz"), _load_npz(records / "episodes.npz"),
                   _load_npz(records / "junction.npz"),
                   (yaml.safe_load(config.read_text()) if config.is_file() else None) or {},
                   _load_npz(rbm) if rbm.is_file() else None)

    # ---- the task ----
    @property
    def experiment(self) -> str:
        return str(self.summary.get("experiment", self.run_dir.name))

    @property
    def n_runs(self) -> int:
        return self.episodes["discounted_return"].shape[0]

    @property
    def n_episodes(self) -> int:
        return self.episodes["discounted_return"].shape[1]

    @property
    def max_steps(self) -> int:
        return self.episodes["td_sampled"].shape[2]

    @cached_property
    def matching(self) -> bool:
        """Matching T-maze: the condition codes both signals, 0–3 (docs/records.md)."""
        return bool(self.episodes["condition"].max() > 1)

    @property
    def digit(self) -> bool:
        """Digit observations (§4.3.3, §5.3.2): a DigitTMaze in the run's config or, without
        a config, "digit" in the experiment's name."""
        target = self.config.get("env", {}).get("_target_")
        return "DigitTMaze" in target if target else "digit" in self.experiment.lower()

    @property
    def variant(self) -> str:
        return ("digit " if self.digit else "") + ("matching" if self.matching else "regular")

    @property
    def chapter4(self) -> bool:
        """The one-predictor model of Algorithm 1, whose figures chapter 4 shows; any other
        set of predictors is the model of Algorithm 2 (chapter 5)."""
        return self.predictors == ["joint"]

    @property
    def numbering(self) -> Numbering:
        if self.chapter4:
            return CH4_MATCHING if self.matching else CH4_REGULAR
        return CH5_DIGIT if self.digit else CH5_BIT

    @cached_property
    def preprocessing(self) -> preproc.Preprocessing | None:
        """The RBM preprocessor's images and codes (Figs. 5.15–5.16); None without one."""
        if self.preprocessor is None:
            return None
        env = self.config.get("env", {})
        return preproc.Preprocessing.from_records(
            self.preprocessor, observation_names(env.get("matching", self.matching)),
            env.get("digit_classes") or {})

    @property
    def optimal_return(self) -> float:
        return float(self.episodes["optimal_return"])

    @property
    def optimal_steps(self) -> float:
        return float(self.episodes["optimal_steps"])

    @property
    def condition_names(self) -> list[str]:
        if self.matching:  # condition = 2·initial + junction signal
            return [f"({s0}, {s1})" for s0 in (0, 1) for s1 in (0, 1)]
        return ["0", "1"]

    @property
    def condition_title(self) -> str:
        return "(initial, junction) signal" if self.matching else "initial signal"

    # ---- predictors (Figs. 4.5/4.10, 5.2/5.17) ----
    @cached_property
    def predictors(self) -> list[str]:
        suffix = "_error_train"
        return sorted(k[:-len(suffix)] for k in self.predictor if k.endswith(suffix))

    def lengths(self, name: str) -> np.ndarray:
        return self.predictor[f"{name}_lengths"].astype(np.int64)

    def epochs(self, name: str) -> np.ndarray:
        return self.predictor[f"{name}_epochs"].astype(np.int64)

    def errors(self, name: str, split: str) -> np.ndarray:
        """(R, E, nT, Tmax+1) Eq. (4.7) errors (chapter 5: figs.ERROR_UNITS), NaN for t > T."""
        return self.predictor[f"{name}_error_{split}"].astype(np.float64)

    @property
    def l_training(self) -> int:
        return int(self.config.get("trainer", {}).get("l_training", L_TRAINING))

    def trained_max(self, name: str) -> int:
        """Longest trained step-length, T_min + L_training − 1 (Algorithms 1–2)."""
        return int(self.lengths(name).min()) + self.l_training - 1

    # ---- behaviour (Figs. 4.6–4.8, 4.11–4.13, 5.3–5.6, 5.18–5.19) ----
    @cached_property
    def curves(self) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        return {key: curve(self.episodes[key]) for key in CURVES}

    def each_run(self, key: str) -> np.ndarray:
        """(R, N − WINDOW + 1) moving average of every run (Figs. 4.6(b), 5.3(b), 5.18(b))."""
        return moving_average(self.episodes[key], WINDOW)

    def optimum(self, key: str) -> float | None:
        target = CURVES[key][1]
        return getattr(self, target) if isinstance(target, str) else target

    def window_mean(self, key: str, first: bool) -> np.ndarray:
        """(R,) mean of the first or last WINDOW episodes of each run."""
        values = self.episodes[key].astype(np.float64)
        return (values[:, :WINDOW] if first else values[:, -WINDOW:]).mean(axis=1)

    def error_trend(self, name: str, early_epochs: float) -> dict[str, float]:
        """Figs. 4.5/4.10/5.2/5.17 in numbers: the error averaged over runs, step-lengths
        and steps t ≥ 1 (t = 0 predicts the random initial signal and cannot improve, §4.3.1).

        `initial`/`final`: training data of the trained lengths at the first/last epoch;
        `early_share`: share of that drop reached by the last logged epoch within the
        first `early_epochs` of training (NaN when none was logged); `test`/`longer`: final
        test error of the trained / the longer, untrained lengths (NaN without the latter).
        """
        trained = self.lengths(name) <= self.trained_max(name)
        train, test = (self.errors(name, split)[..., 1:] for split in ("train", "test"))
        by_epoch = nanmean(train[:, :, trained], axis=(0, 2, 3))
        epochs = self.epochs(name)
        early = np.flatnonzero((epochs > 0) & (epochs <= early_epochs * epochs[-1]))
        drop = by_epoch[0] - by_epoch[-1]
        return {"initial": float(by_epoch[0]), "final": float(by_epoch[-1]),
                "early_share": float((by_epoch[0] - by_epoch[early[-1]]) / drop)
                if early.size and drop > 0 else float("nan"),
                "test": float(nanmean(test[:, -1, trained])),
                "longer": float(nanmean(test[:, -1, ~trained]))}

    def metric(self, name: str) -> np.ndarray:
        return np.asarray(self.summary["metrics"][name], dtype=np.float64)

    # ---- the T-junction (Figs. 4.14–4.19, 5.7–5.13, 5.20–5.25) ----
    @cached_property
    def layers(self) -> list[str]:
        """Activation layers recorded at the junction: memories, actor state, actor hidden."""
        names = [k for k, v in self.junction.items() if k not in VISIT_KEYS and v.ndim == 2]
        rank = {"state": 1, "hidden": 2}
        return sorted(names, key=lambda k: (0 if k.startswith("memory") else rank.get(k, 3), k))

    @property
    def memory_layers(self) -> list[str]:
        return [k for k in self.layers if k.startswith("memory")]

    @cached_property
    def steps_to_goal(self) -> np.ndarray:
        """(K,) length of each visit's episode, read off episodes.npz when not recorded."""
        if "steps_to_goal" in self.junction:
            return self.junction["steps_to_goal"]
        return self.episodes["steps"][self.junction["run"], self.junction["episode"]]

    @property
    def phase_episodes(self) -> int:
        """Episodes per phase: 1000 as in Figs. 4.14–4.19, at most half of a shorter run,
        so that the two phases never overlap."""
        return min(PHASE_EPISODES, self.n_episodes // 2)

    def phase_label(self, phase: str) -> str:
        n = self.phase_episodes
        first = 0 if phase == "first" else self.n_episodes - n
        return f"{phase} {n} episodes ({first}–{first + n - 1})"

    def phase_visits(self, phase: str, r: int) -> np.ndarray:
        episode = self.junction["episode"]
        in_phase = (episode < self.phase_episodes if phase == "first"
                    else episode >= self.n_episodes - self.phase_episodes)
        return np.flatnonzero((self.junction["run"] == r) & in_phase)

    @cached_property
    def _projections(self) -> dict:
        return {}

    def nonfinite_visits(self, layer: str) -> np.ndarray:
        """Visits whose activations are not all finite (a diverged actor); PCA leaves them out."""
        return ~np.isfinite(self.junction[layer].astype(np.float64)).all(axis=1)

    def projection(self, layer: str, phase: str, r: int) -> Projection | None:
        """PCA fit on the finite visits of run r in one phase (None with fewer than 2)."""
        key = (layer, phase, r)
        if key not in self._projections:
            visits = self.phase_visits(phase, r)
            visits = visits[~self.nonfinite_visits(layer)[visits]]
            self._projections[key] = (
                Projection(visits, *pca(self.junction[layer][visits], N_PCS))
                if len(visits) >= 2 else None)
        return self._projections[key]

    def separation_labels(self, layer: str) -> list[str]:
        """Labellings scored per layer: the condition; for memories also the initial signal,
        which they must keep to predict the terminal reward (§4.3.2, Fig. 4.14)."""
        return ["condition", "initial_signal"] if layer in self.memory_layers else ["condition"]

    @cached_property
    def separation(self) -> dict[tuple[str, str], np.ndarray]:
        """(layer, labels) → (phase, run) silhouette of the labels on PC1–3 of each fit."""
        out = {}
        for layer in self.layers:
            for labels in self.separation_labels(layer):
                scores = np.full((len(PHASES), self.n_runs), np.nan)
                for p, phase in enumerate(PHASES):
                    for r in range(self.n_runs):
                        proj = self.projection(layer, phase, r)
                        if proj is None:
                            continue
                        scores[p, r] = subsampled_silhouette(
                            proj.scores, self.junction[labels][proj.visits], MAX_SILHOUETTE_POINTS)
                out[layer, labels] = scores
        return out

    def explained(self, layer: str, phase: str) -> np.ndarray:
        """(R', units) explained-variance ratios of the runs with visits in the phase."""
        projs = [self.projection(layer, phase, r) for r in range(self.n_runs)]
        return np.array([p.explained for p in projs if p is not None]).reshape(
            -1, self.junction[layer].shape[1])


def layer_label(layer: str) -> str:
    named = {"memory_observation": "observation-predictor memory m^y",
             "memory_reward": "reward-predictor memory m^r",
             "state": "actor state (y, m)", "hidden": "actor hidden ĥ"}
    if layer in named or not layer.startswith("memory"):
        return named.get(layer, layer)
    part = layer[len("memory"):].strip("_")
    return f"predictor memory{f' ({part})' if part else ''}"


# ---- data files ------------------------------------------------------------

def write_tables(run: TMazeRun, out: Path) -> list[str]:
    """Write the numbers behind the figures; return the file names."""
    written = []

    def table(name: str, header, rows) -> None:
        _write_csv(out / name, header, rows)
        written.append(name)

    episodes = run.curves["discounted_return"][0]
    columns = [column for key in CURVES for column in run.curves[key][1:]]  # mean, sem
    columns += list(run.each_run("discounted_return"))
    table("learning_curves.csv",
          ["episode", *(f"{k}_ma{WINDOW}_{s}" for k in CURVES for s in ("mean", "sem")),
           *(f"discounted_return_ma{WINDOW}_run_{r}" for r in range(run.n_runs))],
          [(int(e), *(_fmt(c[i]) for c in columns)) for i, e in enumerate(episodes)])

    for name in run.predictors:
        rows = []
        for split in ("train", "test"):
            err = run.errors(name, split)
            first, last = nanmean(err[:, 0], axis=0), nanmean(err[:, -1], axis=0)
            sem = sem_over_runs(err[:, -1])
            for k, T in enumerate(run.lengths(name)):
                rows += [(split, int(T), t, int(T <= run.trained_max(name)), _fmt(first[k, t]),
                          _fmt(last[k, t]), _fmt(sem[k, t]))
                         for t in range(T + 1) if np.isfinite(last[k, t])]
        table(f"prediction_errors_{name}.csv",
              ["split", "T", "t", "trained_length", "epoch0_mean",
               f"epoch{run.epochs(name)[-1]}_mean", f"epoch{run.epochs(name)[-1]}_sem"], rows)

    if run.layers:
        runs = [f"run_{r}" for r in range(run.n_runs)]
        table("junction_separation.csv",
              ["layer", "labels", "phase", "episodes", "runs_defined", "silhouette_mean",
               "silhouette_sem", *runs],
              [(layer, labels, phase, run.phase_label(phase), int(defined.sum()),
                _fmt(nanmean(s[p])), _fmt(float(sem_over_runs(s[p][defined]))), *map(_fmt, s[p]))
               for (layer, labels), s in run.separation.items()
               for p, phase in enumerate(PHASES) for defined in [np.isfinite(s[p])]])
        table("junction_explained_variance.csv", ["layer", "phase", "pc", "mean", "sem"],
              [(layer, phase, k + 1, _fmt(nanmean(ratio[:, k])), _fmt(sem[k]))
               for layer in run.layers for phase in PHASES
               for ratio in [run.explained(layer, phase)] for sem in [sem_over_runs(ratio)]
               for k in range(ratio.shape[1])])
    if run.preprocessing is not None:
        written += preproc.write_tables(run.preprocessing, out)
    return written


# ---- figures ---------------------------------------------------------------

def _junction_figures(run: TMazeRun, layer: str) -> dict[str, tuple]:
    out = {}
    j, r = run.junction, FIGURE_RUN
    mine = j["run"] == r
    what = f"{layer_label(layer)} at the T-junction, run {r}"
    numbers = run.numbering.layer(layer)
    out[f"junction_{layer}_activations"] = (
        figs.junction_activations(j[layer][mine].astype(np.float64), j["condition"][mine],
                                  j["episode"][mine], run.condition_names, run.condition_title,
                                  what),
        f"{numbers.activations}: {what}, every visit, sorted by condition then episode")
    panels, explained = [], []
    for p, phase in enumerate(PHASES):
        proj = run.projection(layer, phase, r)
        if proj is None:
            continue
        scores = ", ".join(f"{LABELLINGS[labels]} {run.separation[layer, labels][p, r]:.2f}"
                           for labels in run.separation_labels(layer))
        panels.append((f"{run.phase_label(phase)}\nsilhouette on PC1–3: {scores}",
                       proj.scores, j["condition"][proj.visits], run.steps_to_goal[proj.visits]))
        explained.append((run.phase_label(phase), proj.explained))
    if not panels:
        return out
    out[f"junction_{layer}_pca"] = (
        figs.junction_pca(panels, explained, run.condition_names, run.condition_title,
                          (run.optimal_steps, run.max_steps),
                          f"{numbers.pca}: {what}: PCA fit separately on each phase's visits; "
                          "marker size = steps to the goal"),
        f"{numbers.pca}: {what}, PC1–2 and explained-variance ratios of the PCA fit on the "
        f"visits of the first and, separately, the last {run.phase_episodes} episodes")
    if numbers.pca3d:
        out[f"junction_{layer}_pca3d"] = (
            figs.junction_pca3d([(t, s, c) for t, s, c, _ in panels], run.condition_names,
                                run.condition_title,
                                f"{numbers.pca3d}: {what}: projection on PC1–3"),
            f"{numbers.pca3d}: {what} on PC1–3, PCA fit per phase as in junction_{layer}_pca")
    return out


def make_figures(run: TMazeRun) -> dict[str, tuple]:
    """name → (Figure, caption) for every chapter-4/5 figure this run's records support."""
    out = {} if run.preprocessing is None else preproc.make_figures(run.preprocessing)
    num = run.numbering
    for name in run.predictors:
        fig_no = num.prediction_figure(name)
        units = figs.ERROR_UNITS.get(name, "prediction error")
        out[f"prediction_errors_{name}"] = (
            figs.prediction_errors(nanmean(run.errors(name, "train"), axis=0),
                                   nanmean(run.errors(name, "test"), axis=0),
                                   run.lengths(name), run.epochs(name), run.trained_max(name),
                                   units,
                                   f"{fig_no}: prediction errors of the `{name}` predictor, "
                                   f"mean over {run.n_runs} runs ({run.variant} T-maze)"),
            f"{fig_no}: {units.splitlines()[0]} of the `{name}` predictor per epoch × step, "
            "train (top) / test (bottom) by step-length T")
    episodes = run.curves["discounted_return"][0]
    panels = [(CURVES[k][0], *run.curves[k][1:], run.optimum(k))
              for k in CURVES if k != "td_abs_mean"]
    out["learning_curves"] = (
        figs.learning_curves(episodes, panels,
                             (CURVES["discounted_return"][0], run.each_run("discounted_return"),
                              run.optimal_return), WINDOW, run.n_runs,
                             f"{num.learning_curves}: {run.variant} T-maze ({run.experiment})"),
        f"{num.learning_curves}: discounted return, steps to the goal, terminal reward and "
        "correct-goal rate; moving average, mean ± s.e.m. over runs, optimum dotted; the "
        "discounted return of each run")
    out["td_errors"] = (
        figs.td_errors(episodes, *run.curves["td_abs_mean"][1:], WINDOW, run.n_runs,
                       run.episodes["td_sampled"][FIGURE_RUN],
                       run.episodes["td_sampled_episodes"],
                       f"{num.td_errors}: TD errors ({run.variant} T-maze)"),
        f"{num.td_errors}: (a) moving average of the episode-mean |δ|, mean ± s.e.m.; "
        f"(b) per-step δ of the sampled episodes of run {FIGURE_RUN}")
    for layer in run.layers:
        out |= _junction_figures(run, layer)
    return out


def _header(run: TMazeRun) -> list[tuple[str, str]]:
    predictors = "; ".join(
        f"`{name}`: T = {run.lengths(name).min()}…{run.lengths(name).max()}, trained on "
        f"T ≤ {run.trained_max(name)} (L_training = {run.l_training}, "
        f"{run.numbering.parameters}), {len(run.epochs(name))} logged epochs up to "
        f"{run.epochs(name)[-1]}" for name in run.predictors)
    junction = (f"{len(run.junction['run'])} visits; layers "
                f"{', '.join(f'`{k}` ({run.junction[k].shape[1]} units)' for k in run.layers)}; "
                f"PCA (SVD) fit per run on the visits of the first and, separately, the last "
                f"{run.phase_episodes} episodes; figures show run {FIGURE_RUN}; separation = "
                f"silhouette of the labels on PC1–3 (≤ {MAX_SILHOUETTE_POINTS} visits per run "
                "and phase)") if run.layers else "no junction activations recorded"
    dropped = {k: int(run.nonfinite_visits(k).sum()) for k in run.layers}
    if any(dropped.values()):
        junction += "; left out for non-finite activations: " + ", ".join(
            f"`{k}` {n} visits" for k, n in dropped.items() if n)
    header = [
        ("run directory", f"`{run.run_dir}`"),
        ("experiment", run.experiment),
        ("seeds", str(run.summary.get("seeds", "?"))),
        ("model", "Algorithm 1, one joint predictor (chapter 4)" if run.chapter4 else
                  "Algorithm 2, separate observation and reward predictors (chapter 5)"),
        ("task", f"{run.variant} T-maze, T_min = {run.optimal_steps:g}, "
                 f"T_max = {run.max_steps}"),
        ("runs × actor episodes", f"{run.n_runs} × {run.n_episodes}"),
        ("optimum", f"discounted return {run.optimal_return:.4f} "
                    f"(γ = {float(run.episodes['gamma']):g}), {run.optimal_steps:g} steps"),
        ("predictors", predictors or "none recorded"),
        ("moving averages", f"{WINDOW} episodes, mean ± s.e.m. over runs"),
        ("junction analysis", junction),
    ]
    if run.preprocessing is not None:
        header.append(("preprocessor", preproc.describe(run.preprocessing)))
    return header


def analyze(run_dir: Path, out: Path) -> RunAnalysis:
    """Analyze one T-maze run; data files go to `out`, figures are returned."""
    run = TMazeRun.load(run_dir)
    return RunAnalysis(title=f"T-maze ({run.variant}): {run.experiment}",
                       header=_header(run), figures=make_figures(run),
                       data_files=write_tables(run, out), results=evaluate(TMAZE_CLAIMS, run))
