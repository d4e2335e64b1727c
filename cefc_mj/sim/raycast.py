"""The MuJoCo world's LiDAR as one compiled call per env, with a horizontal broadphase.

`mj_multiRay` tests every geom of the scene for every beam (bounding angles, then the exact ray-geom
intersection `mju_rayGeom` on the survivors) and keeps the nearest hit. Here the same `mju_rayGeom`
(called through its C address, as `run_physics` calls `mj_step`) is run only on the geoms whose
horizontal bounding circle comes within the LiDAR range of the beam origin, for all drones in one
numba call. A beam's reading is min(range, nearest hit), and a geom left out cannot hit anything
nearer than its horizontal distance minus its horizontal reach (> range), so the readings are those of
`mj_multiRay` bit for bit: the same C function computes each distance, and a minimum does not
depend on the order it is taken in (tests/test_eval_speed_equivalence.py checks it on random layouts,
tilted drones and UAV-UAV beams included). The cost per drone depends on the geoms near it, not on
the scene's size: the LiDAR of a 256-drone swarm costs per drone what an 8-drone group does.
"""

from __future__ import annotations

import ctypes
from pathlib import Path

import mujoco
import numpy as np
from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic

from cefc_mj.jit import njit

REACH_MARGIN = 1e-6
"""Added to every geom's horizontal reach (m): float rounding in the broadphase can only keep a geom."""


def mujoco_symbol_address(name: str) -> int | None:
    """C address of `name` in the MuJoCo library the bindings loaded (None if it cannot be found)."""
    for lib in sorted(Path(mujoco.__file__).parent.glob("libmujoco*")):
        try:
            return ctypes.cast(getattr(ctypes.CDLL(str(lib)), name), ctypes.c_void_p).value
        except (OSError, AttributeError):
            continue
    return None


MJU_RAY_GEOM = mujoco_symbol_address("mju_rayGeom")


@intrinsic
def _ray_geom(typingctx, fn, pos, mat, size, pnt, vec, geomtype):
    """`mjtNum mju_rayGeom(pos, mat, size, pnt, vec, geomtype, normal=NULL)` at address fn (pointers as integers)."""
    sig = types.float64(types.uintp, types.uintp, types.uintp, types.uintp, types.uintp, types.uintp, types.int32)

    def codegen(context, builder, signature, args):
        ptr = ir.IntType(8).as_pointer()
        fnty = ir.FunctionType(ir.DoubleType(), [ptr, ptr, ptr, ptr, ptr, ir.IntType(32), ptr])
        fptr = builder.inttoptr(args[0], fnty.as_pointer())
        pointers = [builder.inttoptr(a, ptr) for a in args[1:6]]
        return builder.call(fptr, pointers + [args[6], ir.Constant(ptr, None)])

    return sig, codegen


@njit
def cast_lidar(
    ray_fn,
    origins,
    altitude,
    directions,
    cutoff,
    geom_xpos,
    geom_xmat,
    geom_size,
    geom_type,
    candidates,
    candidate_body,
    candidate_reach,
    caster_body,
    obstacles,
    obstacle_radius,
    discs,
    disc_radius,
    out,
):
    """LiDAR ranges [N, M] of the drones of one env, as MujocoWorld.lidar defines them.

    Each beam reads its nearest hit as mj_multiRay reports it, `cutoff` (the range) without a hit
    within it; a drone whose origin lies inside (or on) an obstacle circle or another UAV's disc
    reads 0 on every beam.

    origins [N, 2] beam origins (x, y) at `altitude`; directions [M, 3] unit beam directions;
    geom_xpos [G, 3], geom_xmat [G, 9], geom_size [G, 3], geom_type [G]: the env's MjData / MjModel
    arrays; candidates [C]: the geoms the LiDAR can see, candidate_body [C] their bodies,
    candidate_reach [C] how far (horizontally) any point of each lies from its centre (m);
    caster_body [N]: drone i's body, whose geoms its beams skip (mj_multiRay's bodyexclude);
    obstacles [K, 2] obstacle centres; discs [N', 2] the UAVs' true positions (N' = 0 when the LiDAR
    does not see UAVs); out [N, M] receives the ranges."""
    pnt = np.empty(3)
    pnt[2] = altitude
    xpos, xmat, size = geom_xpos.ctypes.data, geom_xmat.ctypes.data, geom_size.ctypes.data
    pnt_p, vec_p = pnt.ctypes.data, directions.ctypes.data
    n_beams = directions.shape[0]
    for i in range(origins.shape[0]):
        pnt[0] = origins[i, 0]
        pnt[1] = origins[i, 1]
        inside = False
        for k in range(obstacles.shape[0]):
            gx = origins[i, 0] - obstacles[k, 0]
            gy = origins[i, 1] - obstacles[k, 1]
            if gx * gx + gy * gy <= obstacle_radius * obstacle_radius:
                inside = True
        for j in range(discs.shape[0]):
            gx = origins[i, 0] - discs[j, 0]
            gy = origins[i, 1] - discs[j, 1]
            if j != i and gx * gx + gy * gy <= disc_radius * disc_radius:
                inside = True
        if inside:  # the particle convention (MuJoCo would report the far wall)
            for m in range(n_beams):
                out[i, m] = 0.0
            continue
        for m in range(n_beams):
            out[i, m] = -1.0
        for c in range(candidates.shape[0]):
            if candidate_body[c] == caster_body[i]:
                continue
            g = candidates[c]
            dx = geom_xpos[g, 0] - pnt[0]
            dy = geom_xpos[g, 1] - pnt[1]
            reach = cutoff + candidate_reach[c]
            if dx * dx + dy * dy > reach * reach:
                continue
            for m in range(n_beams):
                d = _ray_geom(ray_fn, xpos + 24 * g, xmat + 72 * g, size + 24 * g, pnt_p, vec_p + 24 * m, geom_type[g])
                if d >= 0.0 and (d < out[i, m] or out[i, m] < 0.0):
                    out[i, m] = d
        for m in range(n_beams):
            if out[i, m] < 0.0 or out[i, m] > cutoff:  # no hit within the range
                out[i, m] = cutoff
