"""One T-maze run (chapters 4–5) → its figures, data files and judged claims.

`TMazeRun` loads the T-maze records of docs/records.md plus `summary.json` and
derives what the figures and claims share: the Eq. (4.7)–(4.8) prediction errors
of each predictor (Figs. 4.5/4.10), 200-episode moving averages of the behaviour
(Figs. 4.6–4.8, 4.11–4.13) and PCA projections of the activations at the
T-junction with the silhouette of the task conditions on PC1–3 (Figs. 4.14–4.19).
`analyze` writes the numbers into the run's `analysis/` folder and returns the
figures and claims for the report.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np
from scipy.spatial.distance import cdist

from ferl.analysis import tmaze_figures as figs
from ferl.analysis.coding import moving_average, sem_over_runs
from ferl.analysis.floor import _fmt, _load_npz, _write_csv
from ferl.analysis.report import TMAZE_CLAIMS, RunAnalysis, evaluate

TASK = "tmaze"
WINDOW = 200                  # moving-average window of Figs. 4.6–4.8, 4.11–4.13
PHASE_EPISODES = 1000         # "first / last 1000 episodes" of Figs. 4.14–4.19
N_PCS = 3                     # separation is scored on PC1–3, the space of Fig. 4.19(b)
L_TRAINING = 5                # Tables 4.1/4.2; the records do not carry it
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


# ---- numbers -----------------------------------------------------------------

def silhouette_score(points: np.ndarray, labels: np.ndarray) -> float:
    """Mean silhouette coefficient (Rousseeuw, 1987) of a labelling, Euclidean distance.

    s_i = (b_i − a_i) / max(a_i, b_i), with a_i the mean distance of point i to the
    other members of its cluster and b_i the smallest mean distance to another
    cluster; s_i = 0 in a singleton cluster or where a_i = b_i = 0. NaN with fewer
    than two labels.
    """
    x = np.asarray(points, dtype=np.float64)
    classes, idx = np.unique(np.asarray(labels), return_inverse=True)
    if len(classes) < 2:
        return float("nan")
    member = np.eye(len(classes))[idx]                       # (n, k) one-hot
    counts = member.sum(axis=0)
    sums = cdist(x, x) @ member                              # (n, k) distance to each cluster
    rows = np.arange(len(x))
    own = counts[idx]
    a = sums[rows, idx] / np.maximum(own - 1, 1)
    to_other = sums / counts
    to_other[rows, idx] = np.inf
    b = to_other.min(axis=1)
    denom = np.maximum(a, b)
    s = np.where((own > 1) & (denom > 0), (b - a) / np.where(denom > 0, denom, 1.0), 0.0)
    return float(s.mean())


def pca(x: np.ndarray, n_components: int = N_PCS) -> tuple[np.ndarray, np.ndarray]:
    """PCA by SVD of the centred data.

    Returns the scores on the first `n_components` PCs, (n, n_components), zero where
    there are fewer components (samples or units), and the explained-variance ratio
    of every PC, one per unit (zeros past the rank).
    """
    x = np.asarray(x, dtype=np.float64)
    u, s, _ = np.linalg.svd(x - x.mean(axis=0), full_matrices=False)
    k = min(n_components, len(s))
    scores = np.zeros((len(x), n_components))
    scores[:, :k] = u[:, :k] * s[:k]
    ratio = np.zeros(x.shape[1])
    total = np.sum(s ** 2)
    if total > 0:
        ratio[:len(s)] = s ** 2 / total
    return scores, ratio


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


def _subsample(n: int, size: int) -> np.ndarray:
    """The same `size` of n indices every time (deterministic, in order)."""
    if n <= size:
        return np.arange(n)
    return np.sort(np.random.default_rng(0).choice(n, size, replace=False))


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

    @classmethod
    def load(cls, run_dir: Path) -> TMazeRun:
        records = run_dir / "records"
        return cls(run_dir, json.loads((run_dir / "summary.json").read_text()),
                   _load_npz(records / "predictor.npz"), _load_npz(records / "episodes.npz"),
                   _load_npz(records / "junction.npz"))

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
        """Digit observations (§4.3.3); only the experiment's name tells."""
        return "digit" in self.experiment.lower()

    @property
    def variant(self) -> str:
        return ("digit " if self.digit else "") + ("matching" if self.matching else "regular")

    @property
    def chapter4(self) -> bool:
        """The one-predictor model of Algorithm 1, whose figures chapter 4 shows."""
        return self.predictors == ["joint"]

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

    # ---- predictors (Figs. 4.5/4.10) ----
    @cached_property
    def predictors(self) -> list[str]:
        suffix = "_error_train"
        return sorted(k[:-len(suffix)] for k in self.predictor if k.endswith(suffix))

    def lengths(self, name: str) -> np.ndarray:
        return self.predictor[f"{name}_lengths"].astype(np.int64)

    def epochs(self, name: str) -> np.ndarray:
        return self.predictor[f"{name}_epochs"].astype(np.int64)

    def errors(self, name: str, split: str) -> np.ndarray:
        """(R, E, nT, Tmax+1) Eq. (4.7) errors, NaN for t > T."""
        return self.predictor[f"{name}_error_{split}"].astype(np.float64)

    def trained_max(self, name: str) -> int:
        """Longest trained step-length, T_min + L_training − 1 (Algorithm 1)."""
        return int(self.lengths(name).min()) + L_TRAINING - 1

    # ---- behaviour (Figs. 4.6–4.8, 4.11–4.13) ----
    @cached_property
    def curves(self) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        return {key: curve(self.episodes[key]) for key in CURVES}

    def optimum(self, key: str) -> float | None:
        target = CURVES[key][1]
        return getattr(self, target) if isinstance(target, str) else target

    def window_mean(self, key: str, first: bool) -> np.ndarray:
        """(R,) mean of the first or last WINDOW episodes of each run."""
        values = self.episodes[key].astype(np.float64)
        return (values[:, :WINDOW] if first else values[:, -WINDOW:]).mean(axis=1)

    def error_trend(self, name: str, early_epochs: float) -> dict[str, float]:
        """Figs. 4.5/4.10 in numbers: the Eq. (4.8) error averaged over runs, step-lengths
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

    # ---- the T-junction (Figs. 4.14–4.19) ----
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
            self._projections[key] = (Projection(visits, *pca(self.junction[layer][visits]))
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
                        keep = _subsample(len(proj.visits), MAX_SILHOUETTE_POINTS)
                        scores[p, r] = silhouette_score(proj.scores[keep],
                                                        self.junction[labels][proj.visits[keep]])
                out[layer, labels] = scores
        return out

    def explained(self, layer: str, phase: str) -> np.ndarray:
        """(R', units) explained-variance ratios of the runs with visits in the phase."""
        projs = [self.projection(layer, phase, r) for r in range(self.n_runs)]
        return np.array([p.explained for p in projs if p is not None]).reshape(
            -1, self.junction[layer].shape[1])


def layer_label(layer: str) -> str:
    if layer.startswith("memory"):
        part = layer[len("memory"):].strip("_")
        return f"predictor memory{f' ({part})' if part else ''}"
    return {"state": "actor state (y, m)", "hidden": "actor hidden ĥ"}.get(layer, layer)


def _layer_figures(layer: str) -> tuple[str, str]:
    """Dissertation figures of a layer's (activations, PCA + explained variance)."""
    return {"state": ("Fig. 4.15(a)", "Figs. 4.15(b)/4.16"),
            "hidden": ("Fig. 4.17(a)", "Figs. 4.17(b)/4.19(a)")}.get(
        layer, ("Fig. 4.14(a)", "Fig. 4.14(b)"))


# ---- data files ------------------------------------------------------------

def write_tables(run: TMazeRun, out: Path) -> list[str]:
    """Write the numbers behind the figures; return the file names."""
    written = []

    def table(name: str, header, rows) -> None:
        _write_csv(out / name, header, rows)
        written.append(name)

    episodes = run.curves["discounted_return"][0]
    columns = [column for key in CURVES for column in run.curves[key][1:]]  # mean, sem
    table("learning_curves.csv",
          ["episode", *(f"{k}_ma{WINDOW}_{s}" for k in CURVES for s in ("mean", "sem"))],
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
    return written


# ---- figures ---------------------------------------------------------------

def _junction_figures(run: TMazeRun, layer: str) -> dict[str, tuple]:
    out = {}
    j, r = run.junction, FIGURE_RUN
    mine = j["run"] == r
    what = f"{layer_label(layer)} at the T-junction, run {r}"
    fig_a, fig_b = _layer_figures(layer)
    out[f"junction_{layer}_activations"] = (
        figs.junction_activations(j[layer][mine].astype(np.float64), j["condition"][mine],
                                  j["episode"][mine], run.condition_names, run.condition_title,
                                  what),
        f"{fig_a}: {what}, every visit, sorted by condition then episode")
    panels, explained = [], []
    for p, phase in enumerate(PHASES):
        proj = run.projection(layer, phase, r)
        if proj is None:
            continue
        sil = run.separation[layer, "condition"][p, r]
        panels.append((f"{run.phase_label(phase)}\nsilhouette of the conditions on PC1–3: "
                       f"{sil:.2f}", proj.scores, j["condition"][proj.visits],
                       run.steps_to_goal[proj.visits]))
        explained.append((run.phase_label(phase), proj.explained))
    if not panels:
        return out
    out[f"junction_{layer}_pca"] = (
        figs.junction_pca(panels, explained, run.condition_names, run.condition_title,
                          (run.optimal_steps, run.max_steps),
                          f"{what}: PCA fit separately on each phase's visits; "
                          "marker size = steps to the goal"),
        f"{fig_b}: {what}, PC1–2 and explained-variance ratios of the PCA fit on the visits "
        f"of the first and, separately, the last {run.phase_episodes} episodes")
    if layer == "hidden":
        out["junction_hidden_pca3d"] = (
            figs.junction_pca3d([(t, s, c) for t, s, c, _ in panels], run.condition_names,
                                run.condition_title, f"{what}: projection on PC1–3"),
            f"Fig. 4.19(b): {what} on PC1–3, PCA fit per phase as in junction_hidden_pca")
    return out


def make_figures(run: TMazeRun) -> dict[str, tuple]:
    """name → (Figure, caption) for every chapter-4 figure this run's records support."""
    out = {}
    pe, lc, td = ("4.10", "4.11–4.12", "4.13") if run.matching else ("4.5", "4.6–4.7", "4.8")
    for name in run.predictors:
        out[f"prediction_errors_{name}"] = (
            figs.prediction_errors(nanmean(run.errors(name, "train"), axis=0),
                                   nanmean(run.errors(name, "test"), axis=0),
                                   run.lengths(name), run.epochs(name), run.trained_max(name),
                                   f"Fig. {pe}: prediction errors of the `{name}` predictor, "
                                   f"mean over {run.n_runs} runs ({run.variant} T-maze)"),
            f"Fig. {pe}: Eq. (4.8) prediction error of `{name}` per epoch × step, "
            "train (top) / test (bottom) by step-length T")
    episodes = run.curves["discounted_return"][0]
    panels = [(CURVES[k][0], *run.curves[k][1:], run.optimum(k))
              for k in CURVES if k != "td_abs_mean"]
    out["learning_curves"] = (
        figs.learning_curves(episodes, panels, WINDOW, run.n_runs,
                             f"Figs. {lc}: {run.variant} T-maze ({run.experiment})"),
        f"Figs. {lc}: discounted return, steps to the goal, terminal reward and correct-goal "
        "rate; moving average, mean ± s.e.m. over runs, optimum dotted")
    out["td_errors"] = (
        figs.td_errors(episodes, *run.curves["td_abs_mean"][1:], WINDOW, run.n_runs,
                       run.episodes["td_sampled"][FIGURE_RUN],
                       run.episodes["td_sampled_episodes"],
                       f"Fig. {td}: TD errors ({run.variant} T-maze)"),
        f"Fig. {td}: (a) moving average of the episode-mean |δ|, mean ± s.e.m.; "
        f"(b) per-step δ of the sampled episodes of run {FIGURE_RUN}")
    for layer in run.layers:
        out |= _junction_figures(run, layer)
    return out


def _header(run: TMazeRun) -> list[tuple[str, str]]:
    predictors = "; ".join(
        f"`{name}`: T = {run.lengths(name).min()}…{run.lengths(name).max()}, trained on "
        f"T ≤ {run.trained_max(name)} (L_training = {L_TRAINING}, Tables 4.1/4.2), "
        f"{len(run.epochs(name))} logged epochs up to {run.epochs(name)[-1]}"
        for name in run.predictors)
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
    return [
        ("run directory", f"`{run.run_dir}`"),
        ("experiment", run.experiment),
        ("seeds", str(run.summary.get("seeds", "?"))),
        ("task", f"{run.variant} T-maze, T_min = {run.optimal_steps:g}, "
                 f"T_max = {run.max_steps}"),
        ("runs × actor episodes", f"{run.n_runs} × {run.n_episodes}"),
        ("optimum", f"discounted return {run.optimal_return:.4f} "
                    f"(γ = {float(run.episodes['gamma']):g}), {run.optimal_steps:g} steps"),
        ("predictors", predictors or "none recorded"),
        ("moving averages", f"{WINDOW} episodes, mean ± s.e.m. over runs"),
        ("junction analysis", junction),
    ]


def analyze(run_dir: Path, out: Path) -> RunAnalysis:
    """Analyze one T-maze run; data files go to `out`, figures are returned."""
    run = TMazeRun.load(run_dir)
    return RunAnalysis(title=f"T-maze ({run.variant}): {run.experiment}",
                       header=_header(run), figures=make_figures(run),
                       data_files=write_tables(run, out), results=evaluate(TMAZE_CLAIMS, run))
