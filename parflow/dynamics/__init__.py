"""What one strain step is.

* :mod:`.bonded`  -- BondedSystem: geometry -> S, N -> N tau = -b -> V_na (rods)
* :mod:`.heun`    -- StepControl and the Heun integrator with projection on the rod lengths
* :mod:`.engines` -- the engines the run loop drives (bonded models, hard-disc contacts)
"""

from . import rkc  # noqa: F401,E402  (registers the "rkc" integrator in heun.INTEGRATORS)
from . import ros2  # noqa: F401,E402  (registers the "ros2" integrator)
