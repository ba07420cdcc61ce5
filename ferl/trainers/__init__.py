"""Trainers: procedures that build the components from the config and train them into a run.

A trainer is a ``PhasedTrainer`` (``phased``) whose phases reuse across procedures: chapter 3's
``DigitFloorTrainer`` (``floor``: test → ``online`` TD → test) and Algorithms 1–2 (``algorithm``:
[preprocessor fit] → ``episodes`` collection → ``predictor_training`` → ``actor_episodes``).
``job`` builds the components and holds what the phases share.
"""
