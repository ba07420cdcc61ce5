"""Analysis of finished runs: numbers, figures and claim-vs-measurement reports.

What a run gets is decided on what it recorded (`records/run.json`), never on names:

* `records` reads a run: its manifest (`Manifest`, with each predictor's role), summary and
  records files; `io` holds the helpers every module shares (npz in, CSV/JSON/markdown out);
* `generic` gives every run its learning curves, TD errors, prediction errors and summary
  table (figures in `figures`); statistics over runs are `ferl.stats`';
* `floor` (digit floor, `floor_figures`) and `tmaze` (T-junction, `tmaze_figures`, with
  `preprocessor` for the RBM of §5.3.2) add their environment's figures; `coding` holds the
  pure computations behind them (§3.5: Eq. 3.12, the Gram-matrix distance, pairwise mutual
  information; moving averages; PCA and the silhouette of labelled points);
* `claims` is the claim framework (claims as data, verdict rules, chapters and their figure
  numbers); `ch3`, `ch4`, `ch5` hold the dissertation's claims by chapter (`tmaze_claims` the
  measures chapters 4 and 5 share), `sweep_claims` those only a comparison of jobs can judge;
* `dispatch` picks a run's environment analysis and chapter from its facts;
* `report` writes a run's `report.md`, `sweep` a sweep's tables and reproduction report, and
  `runner` does `analyze.py`'s work.
"""
