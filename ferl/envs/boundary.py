"""The boundary between ferl and an outside Gymnasium environment (``env=gymnasium``).

Each run's environment is wrapped in ``Guarded`` (inside the bit encoding, so that the encoder
only ever sees values of the space). It turns three faults of the environment into one report
instead of a crash or silent damage:

* an exception raised by the environment's ``reset`` or ``step``;
* an observation outside its observation space (``within``): wrong shape, a value out of range
  (``[3, 1]`` in ``MultiDiscrete([3, 2])``), NaN — which the encoder would otherwise turn into wrong
  bits or an ``IndexError`` that names neither the environment nor the step;
* a reward that is not a finite number (NaN, ±inf), which would otherwise reach the learner and
  be blamed on it ("non-finite TD error").

Check policy: every observation and every reward, at every reset and step, in the wrapper — not
sampled. A sampled check leaves an unchecked step to be encoded as wrong bits (the fault this
module exists to catch), and the full check is cheap beside what a step costs already: Gymnasium's
``contains`` takes 4 µs on a ``Discrete`` observation, 10 µs on a ``Tuple`` of two, 16 µs on
MiniGrid's 7 × 7 × 3 ``Dict``, against 14–230 µs for the environment's own step (POPGym, MiniGrid,
measured on this machine) and the encoding, table look-up and learner step on top. ``Box``
values are checked for shape and bounds but not for dtype (a float64 observation of a float32
box encodes the same bits). The check runs where the environment runs, so the vector
environments (``SyncVectorEnv``, ``AsyncVectorEnv``'s workers) step as before.

A failed environment is dead for good: ``Guarded`` reports the fault once, through the step's
``info`` (``FAULT``: what went wrong, ``DETAIL``: the exception or the value), with a stand-in
observation (a fixed sample of the space), reward 0 and ``terminated``; from then on it never
calls the environment again — every reset gives the stand-in, every step ends the episode with
reward 0 — so the vector environment stays usable and a resumed run cannot raise again. Its
``ferl_state`` is the environment pickled (generators included: a resumed run steps the same
episodes), or empty once it has failed (it is never stepped again).
"""

import copy
import math
import pickle
import reprlib

import gymnasium
import numpy as np
from gymnasium import spaces

FAULT, DETAIL = "ferl_fault", "ferl_fault_detail"  # the info keys of the step at which an environment failed
SHOWN = reprlib.Repr()  # a value in a report: a few entries of each container, short strings
SHOWN.maxlist = SHOWN.maxtuple = SHOWN.maxdict = 8
SHOWN.maxstring = SHOWN.maxother = 60


def within(space: spaces.Space, x) -> bool:
    """Whether ``x`` is a value of ``space``: Gymnasium's ``contains``, except that a ``Box`` value
    is checked for shape and bounds only (module docstring); Tuple and Dict part by part."""
    if isinstance(space, spaces.Box):
        a = np.asarray(x)
        return (  # dtype kinds: the numbers (np.number) as a character test, at every step of every run
            a.shape == space.shape and a.dtype.kind in "iufc" and bool(((a >= space.low) & (a <= space.high)).all())
        )  # NaN compares False
    if isinstance(space, spaces.Tuple):
        parts = tuple(x) if isinstance(x, (list, tuple, np.ndarray)) else None
        return parts is not None and len(parts) == len(space.spaces) and all(map(within, space.spaces, parts))
    if isinstance(space, spaces.Dict):
        return (
            isinstance(x, dict)
            and x.keys() == space.spaces.keys()
            and all(within(s, x[key]) for key, s in space.spaces.items())
        )
    return bool(space.contains(x))


def one_line(text: str, limit: int = 300) -> str:
    """``text`` on one line (the stderr report is one line), cut to ``limit`` characters."""
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[: limit - 1] + "…"


def raised(error: BaseException) -> tuple[str, str]:
    """(what went wrong, detail) of an exception raised by the environment."""
    return "raised", one_line(f"{type(error).__name__}: {error}")


def violation(space: spaces.Space, observation, reward=0.0) -> tuple[str, str] | None:
    """(what went wrong, detail) if the observation is outside ``space`` or the reward is not a
    finite number; None if both are fine."""
    try:
        inside = within(space, observation)
    except Exception:  # noqa: BLE001 — a value the space cannot even compare is outside it
        inside = False
    if not inside:
        return f"returned an observation outside its space {one_line(str(space), 120)}", one_line(
            SHOWN.repr(observation)
        )
    try:
        finite = math.isfinite(float(reward))
    except (TypeError, ValueError):
        finite = False
    if not finite:
        return f"returned the reward {one_line(SHOWN.repr(reward), 60)}", ""
    return None


class Guarded(gymnasium.Wrapper):
    """One run's outside environment behind the checks of the module docstring. ``ferl_failed``
    says whether it has failed (settable: a resumed run restores it)."""

    def __init__(self, env):
        super().__init__(env)
        self.ferl_failed = False

    # ---- what a checkpoint keeps -----------------------------------------------------------------
    @property
    def ferl_state(self) -> bytes:
        """The environment pickled; empty once it has failed (it is never stepped again)."""
        return b"" if self.ferl_failed else pickle.dumps(self.env)

    @ferl_state.setter
    def ferl_state(self, state: bytes) -> None:
        if state:
            self.env = pickle.loads(state)

    # ---- the checked calls -----------------------------------------------------------------------
    def reset(self, *, seed=None, options=None):
        if self.ferl_failed:
            return self.stand_in(), {}
        try:
            observation, info = self.env.reset(seed=seed, options=options)
        except Exception as e:  # noqa: BLE001 — any error of the outside code is the environment's
            return self.fail(*raised(e))[0], self.fail_info
        fault = violation(self.observation_space, observation)
        if fault is not None:
            return self.fail(*fault)[0], self.fail_info
        return observation, info

    def step(self, action):
        if self.ferl_failed:
            return self.stand_in(), 0.0, True, False, {}
        try:
            observation, reward, terminated, truncated, info = self.env.step(action)
        except Exception as e:  # noqa: BLE001
            return self.fail(*raised(e))
        fault = violation(self.observation_space, observation, reward)
        if fault is not None:
            return self.fail(*fault)
        return observation, reward, terminated, truncated, info

    def fail(self, what: str, detail: str) -> tuple:
        """Dead from now on: the step's result that reports it (stand-in, 0, terminated)."""
        self.ferl_failed = True
        self.fail_info = {FAULT: what, DETAIL: detail}
        return self.stand_in(), 0.0, True, False, self.fail_info

    def stand_in(self):
        """A fixed value of the observation space (its sample under seed 0): the same for every
        run and after a resume), drawn once."""
        if getattr(self, "ferl_stand_in", None) is None:
            space = copy.deepcopy(self.observation_space)
            space.seed(0)
            self.ferl_stand_in = space.sample()
        return self.ferl_stand_in
