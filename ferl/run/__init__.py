"""The plumbing of a run being trained: its directory and checkpoints (``directory``), the
divergence guard (``guard``) and TensorBoard logging (``tensorboard``)."""
