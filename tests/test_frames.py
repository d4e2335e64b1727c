"""MuJoCo `rgb_array` frames (cefc_mj.viz.frames) that read: the camera holds the whole arena, game mode
shows the targets and the adversary, and each drone is drawn as its airframe. Real MuJoCo rendering
(EGL headless); skipped only when no OpenGL context can be made at all.

Positions are checked by projecting world points with the camera MuJoCo actually rendered with (the
scene's `mjvGLCamera`s after `mjv_updateScene`, averaged as `mjr_render` does for a mono view), not
with the renderer's own camera arithmetic."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")  # headless MuJoCo frames; MuJoCo reads it when first imported

import mujoco
import numpy as np
import pytest

import cefc_mj
from cefc_mj.errors import ConfigError

SEED = 27  # an obstacle stands in the near corner (9.0, -9.3); game mode: a target at the near corner (-8, -8)
N_AGENTS = 3  # tab10 blue, orange, green: no UAV ring is red like the adversary


def _env(mode: str, render_size=None):
    try:
        env = cefc_mj.make_env(
            backend="mujoco", n_agents=N_AGENTS, mode=mode, obstacle_density=0.03, seed=SEED, render_mode="rgb_array"
        )
    except ConfigError as e:
        if "needs OpenGL" in str(e):
            pytest.skip(f"no OpenGL context for MuJoCo: {e}")
        raise
    if render_size is not None:
        from cefc_mj.pettingzoo_env import CEFCParallelEnv

        env.close()
        env = CEFCParallelEnv(env.batched, render_mode="rgb_array", render_size=render_size)
    env.reset(seed=SEED)
    for _ in range(8):
        env.step({a: np.array([0.6, 0.4]) for a in env.agents})
    return env


def _project(scene, points: np.ndarray, height: int, width: int) -> np.ndarray:
    """[P, 2] (row, column) pixel coordinates of world points [P, 3] in the last rendered frame."""
    cam = mujoco.mjv_averageCamera(scene.camera[0], scene.camera[1])
    assert not cam.orthographic
    pos, forward, up = (np.array(v, dtype=np.float64) for v in (cam.pos, cam.forward, cam.up))
    right = np.cross(forward, up)
    gap = points - pos
    depth = gap @ forward
    assert (depth > cam.frustum_near).all() and (depth < cam.frustum_far).all()
    half_height = 0.5 * (cam.frustum_top - cam.frustum_bottom)
    half_width = cam.frustum_width or half_height * width / height  # mjr_render's rule
    x = cam.frustum_near * (gap @ right) / depth
    y = cam.frustum_near * (gap @ up) / depth
    ndc_x = (x - cam.frustum_center) / half_width
    ndc_y = (y - 0.5 * (cam.frustum_top + cam.frustum_bottom)) / half_height
    return np.stack([(1.0 - ndc_y) / 2.0 * height, (ndc_x + 1.0) / 2.0 * width], axis=1)


def _entities(env) -> dict[str, np.ndarray]:
    """Named world points [P, 3] that must be in the frame: every UAV, every obstacle's rim at its foot
    and top, the target discs' rims (game mode), the adversary, the anchor (formation mode)."""
    batched, world, cfg = env.batched, env.batched.world, env.config
    drones = world.drone_positions[0]
    points = {f"uav_{i}": drones[i][None] for i in range(cfg.n_agents)}
    compass = np.array([(1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0)])
    for k, centre in enumerate(batched.obstacles[0]):
        rim = centre + cfg.obstacle_radius * compass
        heights = (0.0, world.config.obstacle_height)
        points[f"obstacle_{k}"] = np.concatenate([np.c_[rim, np.full(4, z)] for z in heights])
    if cfg.mode == "cefc":
        for j, target in enumerate(batched.targets[0]):
            points[f"target_{j}"] = np.c_[target + cfg.target_radius * compass, np.zeros(4)]
        points["adversary"] = drones[cfg.n_agents][None]
    else:
        points["anchor"] = np.append(batched.anchor[0], 0.0)[None]
    return points


@pytest.mark.parametrize(
    "mode, render_size", [("cefc", None), ("formation", None), ("cefc", (360, 640)), ("formation", (640, 360))]
)
def test_every_entity_projects_inside_the_frame(mode, render_size):
    env = _env(mode, render_size)
    obstacles = env.batched.obstacles[0]
    assert (np.abs(obstacles[:, 0]) > 8.8).any() and (obstacles[:, 1] < -8.0).any()  # one in a near corner
    if mode == "cefc":
        assert env.batched.world.with_adversary
        assert any(np.allclose(t, (-8.0, -8.0)) for t in env.batched.targets[0])  # a target disc past the near edge
    frame = env.render()
    height, width = frame.shape[:2]
    assert (height, width) == (render_size or (480, 480))
    scene = env._frames.renderer.scene
    outside = {}
    for name, points in _entities(env).items():
        pixels = _project(scene, points, height, width)
        off = (pixels[:, 0] < 0) | (pixels[:, 0] >= height) | (pixels[:, 1] < 0) | (pixels[:, 1] >= width)
        if off.any():
            outside[name] = np.round(pixels[off], 1).tolist()
    assert not outside, f"outside the {height} x {width} frame: {outside}"
    # and the arena is not a speck: its edge spans most of the frame in the tighter direction
    a = env.config.arena_half_size
    corners = _project(scene, np.array([[x, y, 0.0] for x in (-a, a) for y in (-a, a)]), height, width)
    span = (corners.max(axis=0) - corners.min(axis=0)) / (height, width)
    assert span.max() > 0.75, span
    env.close()


def _window(frame, pixel, radius: int) -> np.ndarray:
    row, col = (int(np.rint(v)) for v in pixel)
    patch = frame[max(row - radius, 0) : row + radius + 1, max(col - radius, 0) : col + radius + 1]
    return patch.reshape(-1, 3).astype(int)


def test_game_mode_draws_the_targets_and_the_adversary():
    env = _env("cefc")
    frame = env.render()
    height, width = frame.shape[:2]
    scene = env._frames.renderer.scene
    world, cfg = env.batched.world, env.config
    adversary = _project(scene, world.drone_positions[0, cfg.n_agents][None], height, width)[0]
    near = _window(frame, adversary, 8)
    red = (near[:, 0] > 150) & (near[:, 1] < 90) & (near[:, 2] < 90)
    assert red.sum() >= 8, f"no adversary red around pixel {adversary}"
    for target in env.batched.targets[0]:
        centre = _project(scene, np.append(target, 0.0)[None], height, width)[0]
        patch = _window(frame, centre, 3)
        gold = (patch[:, 0] > 150) & (patch[:, 0] - patch[:, 2] > 60) & (patch[:, 1] - patch[:, 2] > 40)
        assert gold.mean() > 0.8, f"target {target}: not gold at pixel {centre}: {patch[:5].tolist()}"
    env.close()


@pytest.mark.parametrize("mode", ["cefc", "formation"])
def test_each_uav_is_drawn_as_its_airframe(mode):
    """The rendered scene holds each drone's airframe geoms (hull, arms, rotors) at the drone, and the
    frame shows the dark hull at the drone's centre inside a ring in the agent's tab10 colour."""
    env = _env(mode)
    frame = env.render()
    height, width = frame.shape[:2]
    scene = env._frames.renderer.scene
    world, cfg = env.batched.world, env.config
    geoms = [scene.geoms[i] for i in range(scene.ngeom)]
    model_geoms = [g for g in geoms if g.objtype == mujoco.mjtObj.mjOBJ_GEOM]
    tab10 = np.array([(31, 119, 180), (255, 127, 14), (44, 160, 44)])
    for i, position in enumerate(world.drone_positions[0, : cfg.n_agents]):
        parts = [g for g in model_geoms if np.linalg.norm(np.array(g.pos) - position) < 0.45]
        assert len(parts) >= 5 and len({int(g.type) for g in parts}) >= 2, (
            f"uav_{i}: {len(parts)} model geoms drawn at the drone, of types {sorted({int(g.type) for g in parts})}"
        )
        pixel = _project(scene, position[None], height, width)[0]
        centre = _window(frame, pixel, 2)
        hull = (centre.max(axis=1) < 100) & (np.ptp(centre, axis=1) < 40)  # dark, grey
        assert hull.any(), f"uav_{i}: no dark airframe pixel at {pixel}: {centre.tolist()}"
        around = _window(frame, pixel, 14)
        ring = np.linalg.norm(around - tab10[i], axis=1) < 60
        assert ring.sum() >= 6, f"uav_{i}: its tab10 colour {tab10[i].tolist()} is not around pixel {pixel}"
    env.close()
