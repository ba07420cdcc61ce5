"""Analysis of finished runs: numbers, figures and claim-vs-measurement reports.

`coding` holds the pure computations (§3.5: Eq. 3.12, the Gram-matrix distance,
pairwise mutual information; moving averages; PCA and the silhouette of labelled
points), `floor_figures` draws the chapter-3 figures, `floor` turns one digit-floor
run directory into its `analysis/` folder, `tmaze` and `tmaze_figures` do the same
for the T-mazes of chapters 4–5, with `preprocessor` for the RBM preprocessor of
§5.3.2, and `report` holds the dissertation's claims as data and writes `report.md`.
"""
