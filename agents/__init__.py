"""agents: everything that knows the simulator.

* :mod:`agents.pilots` - hand-written pilots;
* :mod:`agents.sim` - the simulator glue (flights recorded from the env, env frames to
  sensor readings);
* :mod:`agents.rl` - belief observation wrappers and stable-baselines3 training;
* :mod:`agents.experiments` - the paper's experiments and the RL experiment;
* :mod:`agents.cli` and :mod:`agents.demo` - ``gpbf`` and ``make demo``.
"""

from agents.pilots import WaypointPilot

__all__ = ["WaypointPilot"]
