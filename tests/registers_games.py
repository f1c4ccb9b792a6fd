"""Importing this module registers a gymnasium game in a namespace of its own, as a game
package such as ale_py does (see `cdrl.data.gymrec.NAMESPACE_PACKAGES`)."""
import gymnasium

GAME = "CdrlTestGames/CartPole-v0"

gymnasium.register(id=GAME, entry_point="gymnasium.envs.classic_control.cartpole:CartPoleEnv")
