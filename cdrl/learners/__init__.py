"""Learners that play the built-in game as they learn, each in its own module behind one
interface (`cdrl.learners.api.Learner`), and their registry.

A run names its learner (`RunConfig.learner`, `cdrl train --learner NAME`); the host loop
(`cdrl.runs.online`) takes any registered learner. Adding one is a module with a `Learner`
subclass and one `register` line here (or in the user's own code, before the run starts).
`world_model` is the learner of the offline runs: the world model alone, teacher-forced on
recorded episodes (`cdrl.runs.offline`).
"""
from __future__ import annotations

from cdrl.learners.api import Learner, train_program
from cdrl.learners.imagination_ac import ImaginationAC
from cdrl.learners.imagined_ascent import ImaginedAscent
from cdrl.learners.mpc_planner import MPCPlanner
from cdrl.learners.one_step_q import OneStepQ
from cdrl.learners.onpolicy_ac import OnPolicyAC
from cdrl.learners.ppo import PPO
from cdrl.learners.thesis_ascent import ThesisAscent

OFFLINE = "world_model"
LEARNERS: dict[str, type[Learner]] = {}
# Old name -> name, kept for one release: runs written before the learners had names still load.
ALIASES: dict[str, str] = {"none": OFFLINE}


def register(cls: type[Learner], aliases: tuple[str, ...] = ()) -> type[Learner]:
    """Make `cls` a learner a run can name (`cls.name`, and each of `aliases`)."""
    taken = set(LEARNERS) | set(ALIASES) | {OFFLINE}
    for name in (cls.name, *aliases):
        if name in taken and LEARNERS.get(ALIASES.get(name, name)) is not cls:
            raise ValueError(f"learner name {name!r} is taken")
    LEARNERS[cls.name] = cls
    ALIASES.update(dict.fromkeys(aliases, cls.name))
    return cls


def canonical(name: str) -> str:
    """The learner's name (an old alias resolved). ValueError naming the choices if unknown."""
    name = ALIASES.get(name, name)
    if name != OFFLINE and name not in LEARNERS:
        raise ValueError(f"unknown learner {name!r}; choose one of {', '.join(names())}")
    return name


def names() -> list[str]:
    """Every learner a run can name, the offline world model first."""
    return [OFFLINE, *LEARNERS]


def learner_class(name: str) -> type[Learner]:
    name = canonical(name)
    if name == OFFLINE:
        raise ValueError(f"{OFFLINE!r} trains offline on recorded episodes; it does not play the game")
    return LEARNERS[name]


register(ThesisAscent, aliases=("rollout",))
register(ImaginedAscent, aliases=("imagine",))
register(ImaginationAC, aliases=("critic",))
register(OneStepQ, aliases=("value",))
register(OnPolicyAC, aliases=("real",))
register(PPO)
register(MPCPlanner)

__all__ = ["ALIASES", "LEARNERS", "OFFLINE", "Learner", "canonical", "learner_class", "names", "register",
           "train_program"]
