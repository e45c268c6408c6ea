"""Gymnasium front end of vcfusion: ``vcfusion/Highway-v0`` (vcfusion.gym.env.HighwayEnv).

Importing this module registers the id. Gymnasium 1.x reads no plugin entry points (its 0.x
``gymnasium.envs`` entry-point group is gone), so the id is registered on import, or by naming
the module in the id:

    import gymnasium
    env = gymnasium.make("vcfusion.gym:vcfusion/Highway-v0", observation="kinematics")

Needs the ``gym`` extra (``pip install vcfusion[gym]``).
"""

import gymnasium

ENV_ID = "vcfusion/Highway-v0"

if ENV_ID not in gymnasium.registry:
    # no TimeLimit: the scenario's simulation.max_time_s truncates an episode (HighwayEnv)
    gymnasium.register(id=ENV_ID, entry_point="vcfusion.gym.env:HighwayEnv", max_episode_steps=None)

__all__ = ["ENV_ID"]
