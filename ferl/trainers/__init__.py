"""Trainers: procedures that build the components from the config and train them into a run.

Every trainer is a ``PhasedTrainer`` (``phased``) written in conf/trainer/*.yaml: its ``phases``
(each a ``_target_`` with its own keys), run in order on one ``Job`` (``job``: the components and
what the phases share), and its ``run`` node (``RunControl``: logging, checkpoints, divergence).
The phases reuse across procedures: chapter 3's test → continuing TD → test (``floor_tests``,
``continuing_td``), Algorithms 1–2's [preprocessor fit] → collection → predictor training → actor
episodes (``observations``, ``episodes``, ``predictor_training``, ``actor_episodes``) and §5.4's
online episodes (``online_episodes``).
"""
