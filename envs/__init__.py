"""Environments for cdrl: a Slither.io-like game as pure JAX functions, its rendering,
the thesis's pre-processing, data-collection policies and gymnasium front ends.

Importing this package registers ``gymnasium.make("cdrl/Slither-v0")`` (and
``gymnasium.make_vec("cdrl/Slither-v0", num_envs=N,
vectorization_mode="vector_entry_point")``).
"""

import gymnasium

from envs.gym_env import PreprocessObservation, SlitherEnv, SlitherVectorEnv
from envs.policies import POLICIES, Policy, get_policy
from envs.preprocess import central_crop, preprocess
from envs.slither import Slither, SlitherParams, SlitherState

ENV_ID = "cdrl/Slither-v0"

if ENV_ID not in gymnasium.registry:
    gymnasium.register(
        id=ENV_ID,
        entry_point="envs.gym_env:SlitherEnv",
        vector_entry_point="envs.gym_env:SlitherVectorEnv",
    )

__all__ = [
    "ENV_ID",
    "POLICIES",
    "Policy",
    "PreprocessObservation",
    "Slither",
    "SlitherEnv",
    "SlitherParams",
    "SlitherState",
    "SlitherVectorEnv",
    "central_crop",
    "get_policy",
    "preprocess",
]
