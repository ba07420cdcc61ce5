"""ferl's one-line warnings on stderr, ``ferl: warning: …``: a run goes on, and says what it did
instead (resumed from an older checkpoint, ran a graph eagerly, fitted a damaged cache again)."""

import sys


def warn(message: str) -> None:
    """One line on stderr, as ferl's other run-time messages (errors: ``ferl: error: …``)."""
    print(f"ferl: warning: {message}", file=sys.stderr)
