"""One digit-floor run (chapter 3) → its chapter figures and data files.

``FloorRun`` reads the digit floor's records (docs/records.md) of a run whose environment is the
digit floor (``env.kind`` in run.json) and derives what the figures and the claims of
``reproduction.ch3`` share: greedy accuracy (Fig. 3.6), median firing rates and their clustering
(Eq. 3.12, Figs. 3.11/3.13) and the pixel–label mutual information (Fig. 3.12). The reward
curve of Fig. 3.4 is one of the generic figures (``ferl.analysis.generic``). ``analyze`` writes the
numbers into the run's ``analysis/`` folder and returns the figures.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from ferl import stats
from ferl.analysis import coding
from ferl.analysis.io import fmt, write_csv
from ferl.analysis.records import Run
from ferl.analysis.report import RunAnalysis
from ferl.run.jsonio import strict_dumps
from reproduction import floor_figures as figs

ENV_KIND = "digit_floor"
MI_BINS = 2  # see coding.pairwise_mutual_information
LINKAGE = "average"
INCLUDE_GOAL_IN_CLUSTERING = False  # see FloorRun.cluster_classes
PHASES = ("before", "after")
PERCEPTUAL_PAIRS = (("1", "7"), ("3", "8"))  # grouped without reward, Fig. 3.11(c)


@dataclass
class FloorRun:
    run: Run
    test: dict[str, np.ndarray]  # records/floor_test.npz
    weights: dict[str, np.ndarray]  # records/weights.npz

    @classmethod
    def load(cls, run: Run) -> FloorRun:
        return cls(run, run.required("floor_test"), run.required("weights"))

    @property
    def summary(self) -> dict:
        return self.run.summary

    # ---- layout of the floor and the test ----
    @cached_property
    def classes(self) -> list[str]:
        return [str(c) for c in self.test["classes"]]

    @cached_property
    def digit_classes(self) -> list[str]:
        """The classes shown as digits: all but the floor's noise tiles (§3.5.3), whose label the
        environment records."""
        return [c for c in self.classes if c != self.run.manifest.env.get("noise_class")]

    @cached_property
    def optimal_action(self) -> np.ndarray:
        return self.test["optimal_action"].astype(np.int64)

    @cached_property
    def action_names(self) -> list[str]:
        return [str(a) for a in self.test["action_names"]]

    @property
    def arrangement(self) -> np.ndarray:
        return self.test["arrangement"].astype(str)

    @property
    def noise_levels(self) -> np.ndarray:
        return self.test["noise_levels"].astype(np.float64)

    @property
    def probe_noise(self) -> float:
        return float(self.test["probe_noise"])

    @property
    def probe_level(self) -> int:
        """Index of the test noise level at which the probes were taken."""
        return int(np.argmin(np.abs(self.noise_levels - self.probe_noise)))

    @property
    def n_runs(self) -> int:
        return self.test["greedy_counts_after"].shape[0]

    @property
    def chance(self) -> float:
        return 1.0 / len(self.action_names)

    @property
    def optimal_reward(self) -> float:
        return float(self.summary["optimal"]["reward_per_step"])

    @property
    def has_optimal_actions(self) -> bool:
        return bool((self.optimal_action >= 0).any())

    @property
    def reward_free(self) -> bool:
        """The "without reward" condition of §3.5.3: the floor delivers no reward."""
        return self.run.manifest.env.get("reward_condition") == "none"

    # ---- behaviour (Figs. 3.4, 3.6) ----
    @cached_property
    def accuracy(self) -> dict[str, np.ndarray]:
        return {p: stats.greedy_accuracy(self.test[f"greedy_counts_{p}"], self.optimal_action) for p in PHASES}

    # ---- population coding (Figs. 3.10–3.13) ----
    @cached_property
    def mfr(self) -> dict[str, np.ndarray]:
        """(R, C, H) median firing rates of Eq. (3.12) per run."""
        return {p: np.stack([coding.median_firing_rates(h) for h in self.test[f"hidden_{p}"]]) for p in PHASES}

    @cached_property
    def cluster_classes(self) -> list[str]:
        """Classes clustered by median firing rate: every tile class but the goal, which the
        agent never observes (it is moved away on entering it, §3.4). With the goal left out,
        the four same-action pairs of §3.5.3 partition the eight classes exactly."""
        goal = str(self.arrangement[1, 1])
        return [c for c in self.classes if c != goal or INCLUDE_GOAL_IN_CLUSTERING]

    @cached_property
    def mfr_linkages(self) -> list[np.ndarray]:
        """Clustering of the after-training MFR distance D (Eq. 3.12) of the cluster classes, per run."""
        return self.linkages("hidden")

    @cached_property
    def _linkage_cache(self) -> dict:
        return {}

    def linkages(self, source: str) -> list[np.ndarray | None]:
        """Per-run average-linkage trees of D = g1ᵀ + 1gᵀ − 2G over the cluster classes, from the
        median over test images of ``hidden`` (Eq. 3.12: actions marginalised with a uniform prior)
        or ``hidden_marginal`` (§3.5.3 fn. 6: actions weighted by the policy P(a|z)); None for a
        run whose activations are not finite (its weights diverged)."""
        if source not in self._linkage_cache:
            idx = [self.classes.index(c) for c in self.cluster_classes]
            self._linkage_cache[source] = [
                coding.linkage_from_distance(coding.gram_distance(coding.median_firing_rates(h[idx]))[1], LINKAGE)
                if np.isfinite(h).all()
                else None
                for h in self.test[f"{source}_after"]
            ]
        return self._linkage_cache[source]

    @cached_property
    def same_action_pairs(self) -> list[tuple[int, int]]:
        return coding.same_action_pairs(self.classes, self.optimal_action)

    def named_pairs(self, names) -> list[tuple[int, int]]:
        """Class-index pairs of the named pairs whose classes are both on this floor."""
        return [
            (self.classes.index(a), self.classes.index(b)) for a, b in names if a in self.classes and b in self.classes
        ]

    def cluster_hits(self, i: int, j: int, source: str = "hidden") -> list[bool]:
        """Per run with finite activations: are classes i and j (indices into classes) merged
        directly in the dendrogram?"""
        a, b = (self.cluster_classes.index(self.classes[k]) for k in (i, j))
        return [coding.pair_forms_cluster(z, a, b) for z in self.linkages(source) if z is not None]

    def median_activation(self, phase: str) -> np.ndarray:
        """(R, C, H) median of the marginal activation (§3.5.3, fn. 6)."""
        return np.median(self.test[f"hidden_marginal_{phase}"], axis=2)

    def selectivity(self, phase: str) -> np.ndarray:
        """(R,) how much the median activation differs between classes, mean over units."""
        return self.median_activation(phase).std(axis=1).mean(axis=1)

    # ---- statistics of the images (Fig. 3.12) ----
    @cached_property
    def mutual_information(self) -> np.ndarray:
        return coding.pairwise_mutual_information(self.test["clean_images"], bins=MI_BINS)

    @cached_property
    def mi_linkage(self) -> np.ndarray | None:
        """Clustering of the digits (noise class excluded, as in Fig. 3.12) by MI."""
        if len(self.digit_classes) < 2:
            return None
        idx = [self.classes.index(c) for c in self.digit_classes]
        return coding.linkage_from_distance(self.mutual_information[np.ix_(idx, idx)], LINKAGE)

    def mi_pair_clusters(self, a: str, b: str) -> bool:
        return coding.pair_forms_cluster(self.mi_linkage, self.digit_classes.index(a), self.digit_classes.index(b))

    @cached_property
    def outlier_class(self) -> int | None:
        """Class of Fig. 3.7: "1" when it has an optimal action, else the first that has."""
        if "1" in self.classes and self.optimal_action[self.classes.index("1")] >= 0:
            return self.classes.index("1")
        candidates = np.flatnonzero(self.optimal_action >= 0)
        return int(candidates[0]) if candidates.size else None


# ---- data files ------------------------------------------------------------


def write_tables(run: FloorRun, out: Path) -> list[str]:
    """Write the numbers behind the figures; return the file names."""
    written = []

    def table(name: str, header, rows) -> None:
        write_csv(out / name, header, rows)
        written.append(name)

    runs = [f"run_{r}" for r in range(run.n_runs)]
    table(
        "greedy_accuracy.csv",
        ["phase", "test_noise", "mean", "sem", *runs],
        [
            (p, fmt(x), fmt(mean), fmt(sem), *map(fmt, acc[:, level]))
            for p, acc in run.accuracy.items()
            for level, x in enumerate(run.noise_levels)
            for mean, sem, _ in [stats.mean_sem(acc[:, level])]
        ],
    )

    table(
        "greedy_counts_probe_noise.csv",
        ["phase", "class", "action", "optimal", "mean", "sd", *runs],
        [
            (p, name, act, int(run.optimal_action[c] == a), fmt(mean), fmt(sd), *counts[:, c, a].tolist())
            for p in PHASES
            for counts in [run.test[f"greedy_counts_{p}"][:, run.probe_level]]
            for c, name in enumerate(run.classes)
            for a, act in enumerate(run.action_names)
            for mean, sd, _ in [stats.mean_sd(counts[:, c, a])]
        ],
    )

    if run.outlier_class is not None:
        c = run.outlier_class
        a = run.optimal_action[c]
        probs = {p: run.test[f"probs_{p}"][0, c, :, a] for p in PHASES}
        table(
            "outlier_probs_run0.csv",
            ["class", "image", "p_optimal_before", "p_optimal_after"],
            [(run.classes[c], k, fmt(b), fmt(f)) for k, (b, f) in enumerate(zip(probs["before"], probs["after"]))],
        )

    units = [f"h{k + 1}" for k in range(run.mfr["after"].shape[2])]
    for p in PHASES:
        table(
            f"median_activation_{p}_run0.csv",
            ["class", *units],
            [(name, *map(fmt, row)) for name, row in zip(run.classes, run.median_activation(p)[0])],
        )
    for r, mfr in enumerate(run.mfr["after"]):
        table(f"mfr_run{r}.csv", ["class", *units], [(name, *map(fmt, row)) for name, row in zip(run.classes, mfr)])
    _, distance = coding.gram_distance(run.mfr["after"][0])
    table(
        "mfr_distance_run0.csv",
        ["class", *run.classes],
        [(name, *map(fmt, row)) for name, row in zip(run.classes, distance)],
    )
    table(
        "mutual_information.csv",
        ["class", *run.classes],
        [(name, *map(fmt, row)) for name, row in zip(run.classes, run.mutual_information)],
    )

    (out / "pair_clusters.json").write_text(strict_dumps(_pair_clusters(run), indent=2) + "\n")
    written.append("pair_clusters.json")
    return written


def _pair_clusters(run: FloorRun) -> dict:
    def entry(i: int, j: int) -> dict:
        hits = run.cluster_hits(i, j)
        marginal = run.cluster_hits(i, j, "hidden_marginal")
        return {
            "pair": [run.classes[i], run.classes[j]],
            "runs_forming_cluster": sum(hits),
            "n_runs": len(hits),
            "per_run": hits,
            "runs_forming_cluster_fn6_activation": sum(marginal),
            "per_run_fn6_activation": marginal,
        }

    return {
        "linkage": LINKAGE,
        "clustered_classes": run.cluster_classes,
        "same_action_pairs": [
            dict(entry(i, j), action=run.action_names[run.optimal_action[i]]) for i, j in run.same_action_pairs
        ],
        "perceptual_pairs": [entry(i, j) for i, j in run.named_pairs(PERCEPTUAL_PAIRS)],
    }


# ---- figures ---------------------------------------------------------------


def make_figures(run: FloorRun, n_outlier_images: int = 40) -> dict[str, tuple]:
    """name → (Figure, caption) for every chapter-3 figure this run's records support."""
    out = {
        "fig3_5_weights": (
            figs.weight_images(run.weights["state_weights_before"][0], run.weights["state_weights_after"][0]),
            "Fig. 3.5: observation→hidden weights before/after training (run 0)",
        )
    }
    noise = f"{100 * run.probe_noise:g} %"
    for panel, p in zip("ab", PHASES):
        counts = run.test[f"greedy_counts_{p}"][:, run.probe_level]
        title = (
            f"Fig. 3.6({panel}): greedy actions of the test images, {p} training\n"
            f"(train noise {noise}, test noise {noise})"
        )
        out[f"fig3_6{panel}_greedy_{p}"] = (
            figs.greedy_count_grid(counts, run.classes, run.arrangement, run.optimal_action, run.action_names, title),
            f"Fig. 3.6({panel}): greedy-action counts per class {p} training",
        )
    if run.has_optimal_actions:
        out["fig3_6_accuracy_vs_noise"] = (
            figs.accuracy_vs_noise(
                run.noise_levels, run.accuracy["before"], run.accuracy["after"], run.probe_noise, run.chance
            ),
            "Fig. 3.6(c)/(d): greedy accuracy vs test noise, before/after training",
        )
    if run.outlier_class is not None:
        c = run.outlier_class
        a = run.optimal_action[c]
        out["fig3_7_outlier"] = (
            figs.outlier_images(
                run.test["probe_images"][c].astype(np.float32),
                run.test["probs_before"][0, c, :, a],
                run.test["probs_after"][0, c, :, a],
                run.classes[c],
                run.action_names[a],
                n_outlier_images,
            ),
            f'Fig. 3.7: test images of "{run.classes[c]}" sorted by P(optimal action)',
        )
    out["fig3_10_median_activation"] = (
        figs.median_activation(run.median_activation("before")[0], run.median_activation("after")[0], run.classes),
        "Fig. 3.10: median hidden activation per class (run 0)",
    )
    what = f"{run.run.experiment}, {run.mfr['after'].shape[2]} hidden nodes"
    shown = next((r for r, z in enumerate(run.mfr_linkages) if z is not None), None)
    if shown is not None:  # the first run whose weights did not diverge
        out["fig3_11_dendrogram_run0"] = (
            figs.mfr_dendrogram(
                run.mfr_linkages[shown],
                run.cluster_classes,
                f"Fig. 3.11/3.13: clustered MFRs after training\n(run {shown}; {what})",
            ),
            f"Figs. 3.11/3.13: MFR dendrogram after training, run {shown}",
        )
    out["fig3_11_dendrogram_all_runs"] = (
        figs.mfr_dendrogram_grid(
            run.mfr_linkages, run.cluster_classes, f"Fig. 3.11/3.13: clustered MFRs after training, every run\n({what})"
        ),
        "Figs. 3.11/3.13: MFR dendrograms after training, every run",
    )
    if run.mi_linkage is not None:
        out["fig3_12_mutual_information"] = (
            figs.mi_dendrogram(run.mi_linkage, run.digit_classes, MI_BINS),
            'Fig. 3.12: digits clustered by pairwise mutual information ("N" excluded)',
        )
    return out


def _header(run: FloorRun) -> list[tuple[str, str]]:
    return [
        ("floor patch", " / ".join(" ".join(row) for row in run.arrangement)),
        (
            "optimal actions",
            ", ".join(
                f"{c} {run.action_names[a] if a >= 0 else 'goal'}" for c, a in zip(run.classes, run.optimal_action)
            ),
        ),
        (
            "reward",
            "none delivered (reward-free condition)" if run.reward_free else f"optimum {run.optimal_reward:g} per step",
        ),
        ("training / probe noise", f"{100 * run.probe_noise:g} %"),
        ("test images per class", str(run.test["probs_after"].shape[2])),
        ("clustering", f"{LINKAGE} linkage; mutual information with {MI_BINS} intensity bins"),
    ]


def analyze(run: Run, out: Path) -> tuple[FloorRun, RunAnalysis] | None:
    """The chapter-3 figures and data files of a digit-floor run, and the run as the claims of
    ``reproduction.ch3`` read it; None for a run without the test images' records (an actor that
    saw the floor's true state, not its images)."""
    if run.records("floor_test") is None:
        return None
    floor = FloorRun.load(run)
    return floor, RunAnalysis(
        f"Digit floor (chapter 3): {run.experiment}",
        _header(floor),
        figures=make_figures(floor),
        data_files=write_tables(floor, out),
    )
