"""One T-maze run (chapters 4–5) → its junction and preprocessor figures and data files.

``TMazeRun`` reads the T-maze records of docs/records.md of a run whose environment is a T-maze
(``env.kind`` in run.json) and derives what its figures and the claims of ``reproduction.ch4`` and
``reproduction.ch5`` share: the behaviour's first and last episodes and the prediction errors'
trend (Eq. 4.8; Figs. 4.5–4.8, 4.10–4.13, 5.2–5.6, 5.17–5.19), and the PCA projections of the
activations at the T-junction with the silhouette of the task conditions and, for memories, of
the initial signal on PC1–3 (Figs. 4.14–4.19, 5.7–5.13, 5.20–5.25). The maze variant comes from
the environment's facts (``matching``, image observations), the optimum from ``episodes.npz``, the
observation names from ``env.observation_names``. Its RBM preprocessor, where run.json names one,
is analysed by ``reproduction.preprocessor`` (Figs. 5.15–5.16). Learning curves, TD errors and
prediction errors are generic figures (``ferl.analysis.generic``). ``analyze`` writes the numbers
into the run's ``analysis/`` folder and returns the figures.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from ferl import stats
from ferl.analysis.claims import LayerFigures, Numbering, caption
from ferl.analysis.coding import nanmean, nonfinite_rows, pca, subsampled_silhouette
from ferl.analysis.generic import FIGURE_RUN
from ferl.analysis.io import fmt, write_csv
from ferl.analysis.records import OBSERVATION, REWARD, PredictorErrors, Run
from ferl.analysis.report import RunAnalysis
from reproduction import preprocessor as preproc
from reproduction import tmaze_figures as figs

ENV_KIND = "tmaze"
PHASE_EPISODES = 1000  # "first / last 1000 episodes" of Figs. 4.14–4.19
N_PCS = 3  # separation is scored on PC1–3, the space of Fig. 4.19(b)
MAX_SILHOUETTE_POINTS = 2000  # visits per run and phase; bounds the O(n²) distances
PHASES = ("first", "last")
LABELLINGS = {"condition": "conditions", "initial_signal": "initial signal"}
MEMORY_LABELS: dict[str | None, str] = {
    OBSERVATION: "observation-predictor memory m^y",
    REWARD: "reward-predictor memory m^r",
}


@dataclass(frozen=True)
class Projection:
    """PCA of one layer over the junction visits of one run in one phase."""

    visits: np.ndarray  # indices into the junction records
    scores: np.ndarray  # (n, N_PCS) coordinates on PC1–3
    explained: np.ndarray  # explained-variance ratio of every PC


@dataclass
class TMazeRun:
    run: Run
    episodes: dict[str, np.ndarray]  # records/episodes.npz
    junction: dict[str, np.ndarray]  # records/probe.npz (the T-junction's visits); {} without any

    @classmethod
    def load(cls, run: Run) -> TMazeRun:
        return cls(run, run.required("episodes"), run.probes() or {})

    # ---- the task ----
    @property
    def env(self) -> dict:
        return self.run.manifest.env

    @property
    def n_runs(self) -> int:
        return self.episodes["discounted_return"].shape[0]

    @property
    def n_episodes(self) -> int:
        return self.episodes["discounted_return"].shape[1]

    @property
    def max_steps(self) -> int:
        return int(self.env["max_steps"])

    @property
    def matching(self) -> bool:
        """The matching T-maze of §4.3.2: a second signal at the junction."""
        return bool(self.env.get("matching"))

    @property
    def digit(self) -> bool:
        """Digit-image observations (§4.3.3, §5.3.2)."""
        return self.run.manifest.image_observations

    @property
    def variant(self) -> str:
        return ("digit " if self.digit else "") + ("matching" if self.matching else "regular")

    @cached_property
    def preprocessing(self) -> preproc.Preprocessing | None:
        """The RBM preprocessor's images and codes (Figs. 5.15–5.16); None without one."""
        records = self.run.records("preprocessor")
        if self.run.manifest.preprocessor is None or records is None:
            return None
        return preproc.Preprocessing.from_records(
            records, self.env["observation_names"], self.env.get("digit_classes") or {}
        )

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
    def predictor(self, role: str) -> PredictorErrors | None:
        """The first recorded predictor of a role (records.py)."""
        return next((p for p in self.run.predictors if p.role == role), None)

    def error_trend(self, p: PredictorErrors, early_epochs: float) -> dict[str, float]:
        """Figs. 4.5/4.10/5.2/5.17 in numbers: the error averaged over runs, step-lengths
        and steps t ≥ 1 (t = 0 predicts the random initial signal and cannot improve, §4.3.1).

        ``initial``/``final``: training data of the trained lengths at the first/last epoch;
        ``early_share``: share of that drop reached by the last logged epoch within the
        first ``early_epochs`` of training (NaN when none was logged); ``test``/``longer``: final
        test error of the trained / the longer, untrained lengths (NaN without the latter).
        """
        trained = p.lengths <= p.trained_max
        train, test = p.train[..., 1:], p.test[..., 1:]
        by_epoch = nanmean(train[:, :, trained], axis=(0, 2, 3))
        early = np.flatnonzero((p.epochs > 0) & (p.epochs <= early_epochs * p.epochs[-1]))
        drop = by_epoch[0] - by_epoch[-1]
        return {
            "initial": float(by_epoch[0]),
            "final": float(by_epoch[-1]),
            "early_share": float((by_epoch[0] - by_epoch[early[-1]]) / drop)
            if early.size and drop > 0
            else float("nan"),
            "test": float(nanmean(test[:, -1, trained])),
            "longer": float(nanmean(test[:, -1, ~trained])),
        }

    # ---- behaviour (Figs. 4.6–4.8, 4.11–4.13, 5.3–5.6, 5.18–5.19) ----
    def window_mean(self, key: str, first: bool) -> np.ndarray:
        """(R,) mean of the first or last ``final_window`` episodes of each run (the run's own)."""
        values, window = self.episodes[key].astype(np.float64), self.run.final_window
        return (values[:, :window] if first else values[:, -window:]).mean(axis=1)

    def metric(self, name: str) -> np.ndarray:
        return self.run.metric(name)

    # ---- the T-junction (Figs. 4.14–4.19, 5.7–5.13, 5.20–5.25) ----
    @cached_property
    def layers(self) -> list[str]:
        """Activation layers recorded at the junction: memories, actor state, actor hidden."""
        names = [k for k, v in self.junction.items() if v.ndim == 2]
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
        in_phase = (
            episode < self.phase_episodes if phase == "first" else episode >= self.n_episodes - self.phase_episodes
        )
        return np.flatnonzero((self.junction["run"] == r) & in_phase)

    @cached_property
    def _projections(self) -> dict:
        return {}

    @cached_property
    def _nonfinite(self) -> dict[str, np.ndarray]:
        """layer → (visits,) activations not all finite; once per run, every projection asks."""
        return {layer: nonfinite_rows(self.junction[layer]) for layer in self.layers}

    def nonfinite_visits(self, layer: str) -> np.ndarray:
        """Visits whose activations are not all finite (a diverged actor); PCA leaves them out."""
        return self._nonfinite[layer]

    def projection(self, layer: str, phase: str, r: int) -> Projection | None:
        """PCA fit on the finite visits of run r in one phase (None with fewer than 2)."""
        key = (layer, phase, r)
        if key not in self._projections:
            visits = self.phase_visits(phase, r)
            visits = visits[~self.nonfinite_visits(layer)[visits]]
            self._projections[key] = (
                Projection(visits, *pca(self.junction[layer][visits], N_PCS)) if len(visits) >= 2 else None
            )
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
                            proj.scores, self.junction[labels][proj.visits], MAX_SILHOUETTE_POINTS
                        )
                out[layer, labels] = scores
        return out

    def explained(self, layer: str, phase: str) -> np.ndarray:
        """(R', units) explained-variance ratios of the runs with visits in the phase."""
        projs = [self.projection(layer, phase, r) for r in range(self.n_runs)]
        return np.array([p.explained for p in projs if p is not None]).reshape(-1, self.junction[layer].shape[1])

    def memory_layer(self, role: str) -> str | None:
        """The junction layer of the memory of the first predictor of a role."""
        p = self.predictor(role)
        return None if p is None or f"memory_{p.name}" not in self.layers else f"memory_{p.name}"

    def layer_key(self, layer: str) -> str:
        """The layer as the dissertation's figures name it: a memory by its predictor's role."""
        if not layer.startswith("memory_"):
            return layer
        role = self.run.manifest.roles.get(layer[len("memory_") :])
        return f"memory_{role}" if role else "memory"

    def layer_label(self, layer: str) -> str:
        named = {"state": "actor state (y, m)", "hidden": "actor hidden ĥ"}
        if not layer.startswith("memory"):
            return named.get(layer, layer)
        role = self.run.manifest.roles.get(layer[len("memory_") :])
        return MEMORY_LABELS.get(role, f"predictor memory ({layer[len('memory_') :]})")


# ---- data files ------------------------------------------------------------


def write_tables(run: TMazeRun, out: Path) -> list[str]:
    """Write the numbers behind the junction and preprocessor figures; return the file names."""
    written = []
    if run.layers:
        runs = [f"run_{r}" for r in range(run.n_runs)]
        write_csv(
            out / "junction_separation.csv",
            ["layer", "labels", "phase", "episodes", "runs_defined", "silhouette_mean", "silhouette_sem", *runs],
            [
                (layer, labels, phase, run.phase_label(phase), n, fmt(mean), fmt(sem), *map(fmt, s[p]))
                for (layer, labels), s in run.separation.items()
                for p, phase in enumerate(PHASES)
                for mean, sem, n in [stats.mean_sem(s[p])]
            ],
        )
        write_csv(
            out / "junction_explained_variance.csv",
            ["layer", "phase", "pc", "mean", "sem"],
            [
                (layer, phase, k + 1, fmt(mean), fmt(sem))
                for layer in run.layers
                for phase in PHASES
                for ratio in [run.explained(layer, phase)]
                for k in range(ratio.shape[1])
                for mean, sem, _ in [stats.mean_sem(ratio[:, k])]
            ],
        )
        written += ["junction_separation.csv", "junction_explained_variance.csv"]
    if run.preprocessing is not None:
        written += preproc.write_tables(run.preprocessing, out)
    return written


# ---- figures ---------------------------------------------------------------


def _junction_figures(run: TMazeRun, layer: str, num: Numbering) -> dict[str, tuple]:
    out = {}
    j, r = run.junction, FIGURE_RUN
    mine = j["run"] == r
    what = f"{run.layer_label(layer)} at the T-junction, run {r}"
    numbers = num.layer(run.layer_key(layer)) or LayerFigures("", "")
    out[f"junction_{layer}_activations"] = (
        figs.junction_activations(
            j[layer][mine],
            j["condition"][mine],
            j["episode"][mine],
            run.condition_names,
            run.condition_title,
            what,
        ),
        caption(numbers.activations, f"{what}, every visit, sorted by condition then episode"),
    )
    panels, explained = [], []
    for p, phase in enumerate(PHASES):
        proj = run.projection(layer, phase, r)
        if proj is None:
            continue
        scores = ", ".join(
            f"{LABELLINGS[labels]} {run.separation[layer, labels][p, r]:.2f}" for labels in run.separation_labels(layer)
        )
        panels.append(
            (
                f"{run.phase_label(phase)}\nsilhouette on PC1–3: {scores}",
                proj.scores,
                j["condition"][proj.visits],
                run.steps_to_goal[proj.visits],
            )
        )
        explained.append((run.phase_label(phase), proj.explained))
    if not panels:
        return out
    out[f"junction_{layer}_pca"] = (
        figs.junction_pca(
            panels,
            explained,
            run.condition_names,
            run.condition_title,
            (run.optimal_steps, run.max_steps),
            caption(numbers.pca, f"{what}: PCA fit separately on each phase's visits; marker size = steps to the goal"),
        ),
        caption(
            numbers.pca,
            f"{what}, PC1–2 and explained-variance ratios of the PCA fit on "
            f"the visits of the first and, separately, the last "
            f"{run.phase_episodes} episodes",
        ),
    )
    if numbers.pca3d:
        out[f"junction_{layer}_pca3d"] = (
            figs.junction_pca3d(
                [(t, s, c) for t, s, c, _ in panels],
                run.condition_names,
                run.condition_title,
                f"{numbers.pca3d}: {what}: projection on PC1–3",
            ),
            f"{numbers.pca3d}: {what} on PC1–3, PCA fit per phase as in junction_{layer}_pca",
        )
    return out


def make_figures(run: TMazeRun, num: Numbering) -> dict[str, tuple]:
    """name → (Figure, caption) for every junction and preprocessor figure this run's records
    support."""
    out = {} if run.preprocessing is None else preproc.make_figures(run.preprocessing)
    for layer in run.layers:
        out |= _junction_figures(run, layer, num)
    return out


def _header(run: TMazeRun, num: Numbering) -> list[tuple[str, str]]:
    predictors = "; ".join(
        f"`{p.name}`: T = {p.lengths.min()}…{p.lengths.max()}, trained on T ≤ {p.trained_max} "
        f"(L_training = {run.run.l_training}{f', {num.parameters}' if num.parameters else ''}), "
        f"{len(p.epochs)} logged epochs up to {p.epochs[-1]}"
        for p in run.run.predictors
    )
    junction = (
        (
            f"{len(run.junction['run'])} visits; layers "
            f"{', '.join(f'`{k}` ({run.junction[k].shape[1]} units)' for k in run.layers)}; "
            f"PCA (SVD) fit per run on the visits of the first and, separately, the last "
            f"{run.phase_episodes} episodes; figures show run {FIGURE_RUN}; separation = "
            f"silhouette of the labels on PC1–3 (≤ {MAX_SILHOUETTE_POINTS} visits per run "
            "and phase)"
        )
        if run.layers
        else "no junction activations recorded"
    )
    dropped = {k: int(run.nonfinite_visits(k).sum()) for k in run.layers}
    if any(dropped.values()):
        junction += "; left out for non-finite activations: " + ", ".join(
            f"`{k}` {n} visits" for k, n in dropped.items() if n
        )
    header = [
        ("maze", f"{run.variant} T-maze, T_min = {run.optimal_steps:g}, T_max = {run.max_steps}"),
        (
            "optimum",
            f"discounted return {run.optimal_return:.4f} "
            f"(γ = {float(run.episodes['gamma']):g}), {run.optimal_steps:g} steps",
        ),
        ("predictor training", predictors or "none recorded"),
        ("junction analysis", junction),
    ]
    if run.preprocessing is not None:
        header.append(("preprocessor analysis", preproc.describe(run.preprocessing)))
    return header


def analyze(run: Run, num: Numbering, out: Path) -> tuple[TMazeRun, RunAnalysis]:
    """The junction and preprocessor figures and data files of a T-maze run, and the run as the
    claims of ``reproduction.ch4`` and ``ch5`` read it."""
    maze = TMazeRun.load(run)
    return maze, RunAnalysis(
        f"T-maze ({maze.variant}): {run.experiment}",
        _header(maze, num),
        figures=make_figures(maze, num),
        data_files=write_tables(maze, out),
    )
