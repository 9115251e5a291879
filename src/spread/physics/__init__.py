"""Physics worlds built from Scenes: simulate, settle, read poses and contacts back (DESIGN §6 Stability).

pybullet (:class:`PhysicsWorld`, the reference) and MuJoCo (:class:`MujocoWorld`, the fast path; MJCF
from the same convex parts, masses and frames, :mod:`spread.physics.mjcf`); MuJoCo Warp
(:class:`MujocoWarpWorld`, the same model with a scene's runs as one batch of worlds, on a GPU or the CPU;
optional extra ``gpu-physics``). Every engine is imported only when a world is created, so importing this
package is cheap.
"""

from spread.physics.contacts import FLOOR, ContactSet  # noqa: F401
from spread.physics.params import BULLET_HULL_MARGIN, PhysicsParams  # noqa: F401
from spread.physics.world import PhysicsWorld, SettleResult  # noqa: F401  (first: the reference engine registers first)
from spread.physics.mujoco_world import MujocoWorld
from spread.physics.params import MujocoParams  # noqa: F401
from spread.physics.warp_world import MujocoWarpParams, MujocoWarpWorld  # noqa: F401
from spread.physics.runs import Displacement, Runs, displacement_stats, simulate_runs  # noqa: F401
from spread.physics.worker import get_world  # noqa: F401
