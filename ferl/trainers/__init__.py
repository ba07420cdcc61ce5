"""Training procedures, one per task; ``train.py`` dispatches on ``cfg.task``."""
