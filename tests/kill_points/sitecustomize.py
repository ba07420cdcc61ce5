"""Loaded at start-up by a Python process with this folder on its PYTHONPATH. Where ``FERL_KILL_AT``
names a moment of ferl's Optuna sweeper (ferl/run/study.py), the process kills itself there by
SIGKILL, as the OOM killer or a pre-empted node would: no handler runs, nothing is flushed
(tests/test_study_storage.py).

* ``between:N``: once the N-th trial's value is told to the study, before the next trial is claimed;
* ``writing:N``: inside the SQLite transaction that tells the N-th trial's value, its rows written
  but not committed (SQLAlchemy's commit of the one transaction of that tell that has rows to commit).
"""

import os
import signal

AT = os.environ.get("FERL_KILL_AT")

if AT:
    import optuna
    from sqlalchemy.engine.default import DefaultDialect

    moment, nth = AT.split(":")
    told = {"values": 0, "now": False}  # values told so far; whether the N-th is being told
    study_tell, dialect_commit = optuna.study.Study.tell, DefaultDialect.do_commit

    def die() -> None:
        os.kill(os.getpid(), signal.SIGKILL)

    def tell(self, trial, values=None, *args, **kwargs):
        told["values"] += values is not None
        told["now"] = values is not None and told["values"] == int(nth)
        out = study_tell(self, trial, values, *args, **kwargs)
        if moment == "between" and told["now"]:
            die()
        told["now"] = False
        return out

    def do_commit(self, connection):
        # a tell commits three times, and only the second has rows to commit (sqlite3's in_transaction)
        if moment == "writing" and told["now"] and connection.in_transaction:
            die()
        return dialect_commit(self, connection)

    optuna.study.Study.tell = tell
    DefaultDialect.do_commit = do_commit
