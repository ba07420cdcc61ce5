"""Online TD training on a continuing task (§3.2): the ``OnlineTD`` phase alone, for tasks that
have nothing to test before or after it (Sallans & Hinton's large-action task);
``conf/trainer/online_td.yaml`` names this class and holds its arguments."""
from ferl.config.params import NonNegative, NonNegativeInt, Positive, PositiveInt, checked
from ferl.interfaces import ContinuingEnvironment
from ferl.trainers.online import OnlineTD
from ferl.trainers.phased import PhasedTrainer


class OnlineTDTrainer(PhasedTrainer):
    """``steps`` online TD steps of every run (``OnlineTD``; ``compile``, a root key, compiles its
    chunks); subclasses put phases around them (``around``)."""

    environment = ContinuingEnvironment

    @checked
    def __init__(self, steps: PositiveInt, log_every: PositiveInt, checkpoint_every: PositiveInt,
                 checkpoint_minutes: NonNegative, divergence_limit: Positive, compile_group_runs: PositiveInt,
                 prefetch: NonNegativeInt):
        self.params = dict(steps=steps, log_every=log_every, checkpoint_every=checkpoint_every,
                           checkpoint_minutes=checkpoint_minutes, divergence_limit=divergence_limit)
        self.last_step = steps
        online = OnlineTD(steps, log_every, checkpoint_every, checkpoint_minutes, compile_group_runs, prefetch)
        super().__init__(self.around(online), divergence_limit)

    def around(self, online: OnlineTD) -> list:
        """The phases of a run, given the online TD phase."""
        return [online]
