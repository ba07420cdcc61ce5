"""Batched environments: every run of a batch has its own copy, advanced by one tensor op.

Importing the package registers their Gymnasium views (``ferl.envs.gym``, docs/usage.md).
"""

from ferl.envs.gym import register_envs

register_envs()
