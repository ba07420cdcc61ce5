"""Config plumbing: the types and ranges of component arguments (``params``), the checks of a
composed config before any work (``validate``) and train.py's Hydra glue (``hydra_glue``)."""
