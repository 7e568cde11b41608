"""Ray traversal of octrees, DAGs and dense grids: first voxel hit, front to back.

Three traversals share one ray set-up and one driver:

* ``"stack"``: the talk in ``shared/seeds/000``. A node and a child index are the state;
  the first child comes from comparing the entry ``t`` with the mid-plane ``t``'s, the
  next child from the nearest exit plane (the "moved bit"); going down saves the parent
  with its next child on a stack no deeper than the tree ("save state and go down");
  an exhausted node pops one level per step.
* ``"esvo"``: Laine and Karras' PUSH / ADVANCE / POP (``shared/seeds/002``). The state
  is a cell (level and integer corner) and the stack holds node rows only. PUSH enters
  an occupied cell's first child; ADVANCE steps to the face neighbour across the nearest
  exit plane, and POP happens in the same step: the highest bit that changed in the
  corner names the common ancestor, so any number of levels is popped at once.
* `trace_dense`: Amanatides and Woo's DDA over a dense occupancy grid.

All three mirror negative directions (the coordinate becomes ``R - x`` and the child
slot is XORed with the sign bits), so the loop bodies only handle positive directions,
and stop at the first occupied voxel, which is the nearest because cells are visited
in ray order.

Hit convention: a voxel is hit when the ray passes through its interior at some
``t > 0``, that is when its slab interval ``[t_in, t_out]`` has ``t_in < t_out`` and
``t_out > 0`` (a ray starting on a face and moving away does not hit it; a ray that
only touches an edge or a corner does not either: a traversal visits one of the cells
meeting there, not all), and only if it enters the voxel at ``t <= t_max``. A zero
direction component is replaced by ``2^-100``, so a ray lying exactly in a voxel face
plane passes through the voxels on the positive side of that plane.

Work is in grid units (voxel ``(i, j, k)`` spans ``[i, i+1] x [j, j+1] x [k, k+1]``,
``o = (origin - grid.origin) / h``, ``d = direction / h``), so ``t`` is the parameter of
the world-space ray ``origin + t * direction``.

The driver. A vmapped `jax.lax.while_loop` runs every lane until the slowest ray ends.
By default the rays are instead fed to a fixed number of lanes (persistent threads,
Aila and Laine 2009): every few steps the lanes whose ray ended write its result and
take the next ray from a queue, so lanes do uniform work until the queue is empty.
Rays that miss the grid box never enter the queue. ``lanes=None`` gives the plain
vmapped loop (one lane per ray).
"""

from jaxvox._core.hit import HIT, INVALID, MISS, STEP_CAP, Hit, valid_rays
from jaxvox.trace.api import TRACE_METHODS, jit_trace, trace, trace_dense
from jaxvox.trace.ray import default_max_steps

__all__ = [
    "HIT",
    "Hit",
    "INVALID",
    "MISS",
    "STEP_CAP",
    "TRACE_METHODS",
    "default_max_steps",
    "jit_trace",
    "trace",
    "trace_dense",
    "valid_rays",
]
