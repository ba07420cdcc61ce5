"""ferl's Optuna sweeper for Hydra (``hydra/sweeper=ferl_optuna``): a study in a database file that
outlives the process, resumable, shared by several worker processes (docs/sweeps.md)."""
