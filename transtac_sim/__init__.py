"""transtac_sim: physically based simulator and synthetic-data generator for the TransTac sensor.

Stages (one subpackage each, in data-flow order): ``config`` (scene, hardware and material files),
``sensor`` (assembly, marker layouts), ``indenters``, ``meshing`` (gel tet mesh, marker embedding),
``physics`` (Warp FEM), ``rendering`` (Mitsuba), ``camera`` (lens and sensor model), ``labels``,
``writer``, ``dataset`` (generation). ``perception`` is the real-device pipeline (detection, tracking) that
consumes the data; it never imports the simulator's stages. ``cli`` is the ``transtac-sim`` command.
"""

__version__ = "0.1.0"
