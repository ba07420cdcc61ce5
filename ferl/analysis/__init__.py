"""Analysis of finished runs: numbers, figures and claim-vs-measurement reports.

What a run gets is decided on what it recorded (``records/run.json``), never on names:

* ``records`` reads a run: its manifest (``Manifest``, with each predictor's role), summary and
  records files; ``io`` holds the helpers every module shares (npz in, CSV/JSON/markdown out);
* ``generic`` gives every run its learning curves, TD errors, prediction errors and summary
  table (figures in ``figures``); statistics over runs are ``ferl.stats``'; ``coding`` holds pure
  computations on recorded activations (moving averages, PCA and the silhouette of labelled
  points, the Gram-matrix distance of Eq. 3.12, pairwise mutual information);
* ``claims`` is the claim framework: claims as data, verdict rules, chapters and their figure
  numbers; it holds no claim itself;
* ``dispatch`` holds the registry through which analyses beyond the generic ones plug in (an
  environment's own figures by ``env.kind``, chapters of claims chosen by a run's facts, sweep
  sections); the dissertation's are the top-level package ``reproduction``, which ferl never
  imports;
* ``report`` writes a run's ``report.md``, ``sweep`` a sweep's tables and claims report, ``members``
  finds a sweep's unfinished members, and ``runner`` does ``analyze.py``'s work.
"""
