"""Robots: the registry (``load_robot``), URDF import into MuJoCo, the scenes built around them.

- :mod:`~mjx_pathtrack.robots.registry`: ``Robot``, ``load_robot``, ``known_robots``;
- :mod:`~mjx_pathtrack.robots.scene`: what a robot's MuJoCo model gets beyond its URDF
  (servos, floor contacts, solver settings, target sites);
- :mod:`~mjx_pathtrack.robots.collision`: self-collision checks;
- :mod:`~mjx_pathtrack.robots.urdf_import`: URDF parsing; :mod:`~mjx_pathtrack.robots.iiwa`: the iiwa's limits;
- :mod:`~mjx_pathtrack.robots.ball_scene`: the plate-and-ball scene of the ball task.
"""
