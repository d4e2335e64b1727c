"""Frames of `render_mode="rgb_array"` (cefc_mj.pettingzoo_env): `TopDownFrames` draws the particle
world from above with numpy; `MujocoFrames` renders the quadrotor world offscreen with MuJoCo.

MuJoCo camera rule (`fit_camera`): a free camera at a fixed look angle (azimuth 90 degrees, x to
the right as in the top-down frames; elevation `VIEW_ELEVATION`) and field of view (`VIEW_FOVY`),
placed for the frame's aspect ratio as close as it can be while every corner of the box to be shown
projects inside the frame (`view_box`: the floor out to the arena's edge, in game mode out to the
target discs, the arena up to the obstacles' tops, all plus `VIEW_MARGIN`). Position and distance
are solved in closed form from the arena size, the aspect ratio and the field of view, so any arena
or render size is framed the same way: edge to edge in the tighter direction, centred in the other.
"""

from __future__ import annotations

import atexit
import copy
import dataclasses
import itertools
import math
import weakref
from typing import TYPE_CHECKING

import numpy as np

from cefc_mj.errors import ConfigError
from cefc_mj.sim.particle import ParticleWorld
from cefc_mj.task.config import TaskConfig

if TYPE_CHECKING:
    from cefc_mj.env import BatchedCEFCEnv

VIEW_MARGIN = 1.0
"""Room (m) the MuJoCo frames leave around what they must show, as the top-down frames show the
arena plus 1 m."""
VIEW_ELEVATION = -70.0
"""Elevation (degrees) of the MuJoCo frames' camera: steep enough that the drones are seen from above
(their arms and rotors spread out) and nothing hides behind an obstacle for long, oblique enough
that the obstacles read as cylinders."""
VIEW_AZIMUTH = 90.0
"""Azimuth (degrees): the camera looks along +y, so x grows to the right as in the top-down frames."""
VIEW_FOVY = 30.0
"""Vertical field of view (degrees) of the MuJoCo frames' camera (MuJoCo's default is 45): a longer
lens from further away, so that near and far drones look alike and obstacles stand nearly upright."""
RING_MIN_PX = 7.0
"""Smallest radius (pixels) of the ring in each UAV's colour around its airframe: at 1:200 an Iris
is about 15 pixels across in a 480-pixel frame, a Crazyflie 2, so the ring makes every drone findable."""
RING_WIDTH_PX = 2.5
"""Width (pixels) of the rings, the arena border and the target outlines."""
ADVERSARY_RGBA = (0.85, 0.1, 0.08, 1.0)
"""The adversary's airframe and ring (the top-down frames draw it red too)."""
TARGET_RGBA = (0.9, 0.7, 0.0)
ANCHOR_RGBA = (0.17, 0.63, 0.17)
_BORDER_RGBA = (0.3, 0.3, 0.32, 1.0)
_FLOOR_LIGHTNESS = 0.7
"""The floor texture is lightened this much towards white (dark airframes on a light floor)."""
_VISUAL_GROUP = 3  # cefc_mj.sim.mujoco_world's geom group of the airframe's visual geoms
_ZERO3, _EYE9 = np.zeros(3), np.eye(3).ravel()


def frame_renderer(batched: BatchedCEFCEnv, size: tuple[int, int]):
    """The frame source of `render_mode="rgb_array"` for env 0 of `batched`: `TopDownFrames` for
    the particle world, `MujocoFrames` for a MuJoCo one; ConfigError for a bad size."""
    try:
        height, width = (int(v) for v in size)
    except (TypeError, ValueError):
        raise ConfigError(f"render_size={size!r}: must be (height, width) in pixels") from None
    if height < 16 or width < 16:
        raise ConfigError(f"render_size={size!r}: must be at least 16 x 16 pixels")
    if isinstance(batched.world, ParticleWorld):
        return TopDownFrames(batched.config, height, width)
    if hasattr(batched.world, "models") and hasattr(batched.world, "datas"):
        return MujocoFrames(batched.world, batched.config, height, width)
    raise ConfigError(f"render_mode='rgb_array': no renderer for a {type(batched.world).__name__}")


def _agent_colors(n: int) -> np.ndarray:
    """[n, 3] uint8: UAV i in tab10 colour i, as the top-down plots draw them."""
    import matplotlib

    return (np.asarray(matplotlib.colormaps["tab10"].colors)[np.arange(n) % 10] * 255).round().astype(np.uint8)


class TopDownFrames:
    """Particle-world frames: the arena from above, drawn with numpy (no GL, no figure).

    1 m grid, the arena's border, obstacles (grey), in formation mode the anchor and its 1 m zone
    (green), in cefc mode the target areas (gold) and the adversary (red), and each UAV as its
    footprint disc in its tab10 colour (cefc_mj.viz.plots' colours). The view spans the arena plus
    1 m; a UAV outside it is not drawn. x grows to the right, y upwards.
    """

    def __init__(self, config: TaskConfig, height: int, width: int):
        self.config = config
        half = config.arena_half_size + 1.0
        self.scale = min(height, width) / (2.0 * half)  # pixels per metre
        # world coordinates of the pixel centres
        self.x = (np.arange(width) + 0.5 - width / 2) / self.scale
        self.y = (height / 2 - np.arange(height) - 0.5) / self.scale
        self.colors = _agent_colors(config.n_agents)
        xx, yy = np.meshgrid(self.x, self.y)
        background = np.full((height, width, 3), 250, dtype=np.uint8)
        on_grid = (np.abs(xx - np.round(xx)) < 0.5 / self.scale) | (np.abs(yy - np.round(yy)) < 0.5 / self.scale)
        background[on_grid] = 225
        a = config.arena_half_size
        box_distance = np.maximum(np.abs(xx), np.abs(yy))
        background[(box_distance >= a) & (box_distance <= a + 1.0 / self.scale)] = 90  # the arena's border
        self.background = background

    def frame(self, batched: BatchedCEFCEnv) -> np.ndarray:
        cfg, world = self.config, batched.world
        img = self.background.copy()
        for centre in batched.obstacles[0]:
            self._disc(img, centre, cfg.obstacle_radius, (140, 140, 140))
        if cfg.mode == "formation":
            self._disc(img, batched.anchor[0], cfg.navigation_tolerance, (44, 160, 44), alpha=0.15)
            self._ring(img, batched.anchor[0], cfg.navigation_tolerance, (44, 160, 44))
            self._disc(img, batched.anchor[0], 0.15, (44, 160, 44))
        else:
            for target in batched.targets[0]:
                self._disc(img, target, cfg.target_radius, (230, 180, 0), alpha=0.2)
                self._ring(img, target, cfg.target_radius, (230, 180, 0))
            if cfg.adversary != "none":
                self._disc(img, world.adversary_pos[0], cfg.uav_radius * 1.2, (200, 0, 0))
        for i, pos in enumerate(world.agent_pos[0]):
            self._disc(img, pos, cfg.uav_radius + 1.0 / self.scale, (0, 0, 0))  # outline
            self._disc(img, pos, cfg.uav_radius, self.colors[i])
        return img

    def close(self) -> None:
        pass

    def _window(self, centre, radius):
        """Row and column index ranges of the pixels within `radius` of `centre` (maybe empty)."""
        cols = np.flatnonzero(np.abs(self.x - centre[0]) <= radius)
        rows = np.flatnonzero(np.abs(self.y - centre[1]) <= radius)
        return rows, cols

    def _distance(self, centre, radius):
        rows, cols = self._window(centre, radius)
        if not len(rows) or not len(cols):
            return None, None
        box = np.s_[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]
        d = np.hypot(self.x[cols][None, :] - centre[0], self.y[rows][:, None] - centre[1])
        return box, d

    def _disc(self, img, centre, radius, color, alpha: float = 1.0) -> None:
        box, d = self._distance(centre, radius)
        if box is None:
            return
        inside = d <= radius
        patch = img[box]
        patch[inside] = (1 - alpha) * patch[inside] + alpha * np.asarray(color, dtype=np.float64)

    def _ring(self, img, centre, radius, color) -> None:
        box, d = self._distance(centre, radius)
        if box is None:
            return
        img[box][np.abs(d - radius) <= 1.0 / self.scale] = color


class MujocoFrames:
    """MuJoCo-world frames from `mujoco.Renderer`, of env 0 of the world.

    Renders its own copy of the world's scene, compiled with the airframe's visual geoms (the world
    leaves them out for speed; `MujocoWorldConfig.visual_geoms`) and posed from env 0 before each
    frame (drones from qpos, obstacles from body_pos): each drone is its airframe at its true pose,
    the adversary's tinted red. On top, each UAV gets a ring in its tab10 colour around its airframe
    (at least `RING_MIN_PX` in radius) and the adversary a red one, the arena its border, formation
    mode the anchor's zone (green) and game mode the target discs (gold, with their radius). The
    floor is lightened so that the dark airframes stand out. Camera: `fit_camera` (module docstring).
    Needs OpenGL: headless, MUJOCO_GL=egl (`prefer_headless_gl`). The renderer is created here, so
    a missing GL fails at construction with ConfigError.

    Attributes: `model`, `data` (what is rendered), `camera` (the mujoco.MjvCamera), `option` (the
    mujoco.MjvOption: its geom groups), `renderer` (its `scene` holds the last frame's geoms and
    camera).
    """

    def __init__(self, world, config: TaskConfig, height: int, width: int):
        import mujoco

        self.mujoco = mujoco
        self.world = world
        self.config = config
        source = world.models[0]
        limit = (source.vis.global_.offheight, source.vis.global_.offwidth)
        if height > limit[0] or width > limit[1]:
            raise ConfigError(
                f"render_size=({height}, {width}): the MuJoCo scene renders at most {limit[0]} x {limit[1]}"
            )
        self.height, self.width = height, width
        self.n_agents = config.n_agents
        n_drones = int(getattr(world, "n_drones", self.n_agents))
        self.drone_bodies = np.asarray(getattr(world, "drone_body_ids", np.arange(1, n_drones + 1)), dtype=int)
        self.has_adversary = n_drones > self.n_agents
        self.model = _render_model(world)
        self.data = mujoco.MjData(self.model)
        self.model.vis.global_.fovy = VIEW_FOVY

        top = float(getattr(getattr(world, "config", None), "obstacle_height", 4.0))
        box = view_box(config, top)
        lookat, distance = fit_camera(box, VIEW_ELEVATION, VIEW_AZIMUTH, VIEW_FOVY, width / height)
        self.camera = mujoco.MjvCamera()
        self.camera.type = mujoco.mjtCamera.mjCAMERA_FREE
        self.camera.lookat[:] = lookat
        self.camera.distance = distance
        self.camera.elevation = VIEW_ELEVATION
        self.camera.azimuth = VIEW_AZIMUTH
        self._forward = _forward(VIEW_ELEVATION, VIEW_AZIMUTH)
        self._eye = lookat - distance * self._forward
        self._metres_per_pixel = 2.0 * math.tan(math.radians(VIEW_FOVY) / 2.0) / height  # per metre of depth
        self.model.stat.extent = float(np.linalg.norm(box - self._eye, axis=1).max())  # sets the near/far planes

        self.option = mujoco.MjvOption()  # floor, obstacles, the airframes' visual geoms
        self.option.geomgroup[:] = 0
        has_visuals = (self.model.geom_group == _VISUAL_GROUP).any()
        for group in (0, 1, _VISUAL_GROUP) if has_visuals else (0, 1, 2, 4):  # else the footprint discs
            self.option.geomgroup[group] = 1
        drone_of_geom = self.model.body_rootid[self.model.geom_bodyid]  # the drone body each geom rides on
        mujoco.mj_kinematics(self.model, self.data)  # qpos0: level drones, to measure the airframe
        first = np.flatnonzero(drone_of_geom == self.drone_bodies[0])
        offsets = np.linalg.norm(self.data.geom_xpos[first, :2] - self.data.xpos[self.drone_bodies[0], :2], axis=1)
        self._reach = float(np.max(offsets + self.model.geom_rbound[first])) if len(first) else config.uav_radius
        if self.has_adversary:
            tint = (drone_of_geom == self.drone_bodies[self.n_agents]) & (self.model.geom_rgba[:, 3] == 1.0)
            self.model.geom_rgba[tint] = ADVERSARY_RGBA
            self.model.geom_matid[tint] = -1
        _lighten_floor(mujoco, self.model, float(np.abs(box[:, :2]).max()))
        try:
            self.renderer = mujoco.Renderer(self.model, height, width)
        except Exception as e:  # a missing GL surfaces as FatalError, GLError, ImportError, ... depending on MUJOCO_GL
            hint = str(e).strip().splitlines()[0][:160] if str(e).strip() else type(e).__name__
            raise ConfigError(
                f"render_mode='rgb_array' on MuJoCo needs OpenGL offscreen rendering ({hint}); headless, set "
                f"MUJOCO_GL=egl (or osmesa) before mujoco is imported, or use backend='particle'"
            ) from None
        atexit.register(_close_if_alive, weakref.ref(self))  # before EGL's own exit hook tears the display down
        for flag in (mujoco.mjtRndFlag.mjRND_SHADOW, mujoco.mjtRndFlag.mjRND_REFLECTION):
            self.renderer.scene.flags[flag] = 0  # a third of the time per frame on a software GL
        self.colors = np.concatenate([_agent_colors(config.n_agents) / 255.0, np.ones((config.n_agents, 1))], axis=1)

    def frame(self, batched: BatchedCEFCEnv) -> np.ndarray:
        cfg = self.config
        self._pose()
        self.renderer.update_scene(self.data, camera=self.camera, scene_option=self.option)
        scene = self.renderer.scene
        a = cfg.arena_half_size
        border = np.array([(-a, -a, 0.01), (a, -a, 0.01), (a, a, 0.01), (-a, a, 0.01), (-a, -a, 0.01)])
        self._polyline(scene, border, _BORDER_RGBA)
        if cfg.mode == "formation":
            anchor = np.append(batched.anchor[0], 0.02)
            self._disc(scene, anchor, cfg.navigation_tolerance, (*ANCHOR_RGBA, 0.5))
            self._polyline(scene, _circle(anchor, cfg.navigation_tolerance, 48), (*ANCHOR_RGBA, 1.0))
        else:
            for target in batched.targets[0]:
                centre = np.append(target, 0.02)
                self._disc(scene, centre, cfg.target_radius, (*TARGET_RGBA, 0.4))
                self._polyline(scene, _circle(centre + (0.0, 0.0, 0.01), cfg.target_radius, 96), (*TARGET_RGBA, 1.0))
        drones = self.data.xpos[self.drone_bodies]
        for i in range(self.n_agents):
            self._ring(scene, drones[i], self.colors[i])
        if self.has_adversary:  # a diamond, thicker: tab10 has a red too
            self._ring(scene, drones[self.n_agents], ADVERSARY_RGBA, corners=4, width=1.6)
        return self.renderer.render()

    def close(self) -> None:
        renderer, self.renderer = getattr(self, "renderer", None), None
        if renderer is not None:
            renderer.close()

    # ------------------------------------------------------------------ helpers
    def _pose(self) -> None:
        """Env 0's drones (qpos) and obstacles (body_pos, where the world moves them) into the copy."""
        mujoco, source_model, source = self.mujoco, self.world.models[0], self.world.datas[0]
        self.data.qpos[:] = source.qpos
        self.model.body_pos[:] = source_model.body_pos
        self.model.body_quat[:] = source_model.body_quat
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_camlight(self.model, self.data)

    def _pixels(self, point) -> float:
        """Metres a pixel spans at `point`'s depth."""
        return float(np.dot(np.asarray(point) - self._eye, self._forward)) * self._metres_per_pixel

    def _ring(self, scene, centre, rgba, corners: int = 32, width: float = 1.0) -> None:
        """A horizontal ring (a polygon of `corners` corners, `width` x RING_WIDTH_PX wide) around the
        airframe at `centre`, at least RING_MIN_PX in radius."""
        radius = max(1.3 * self._reach, RING_MIN_PX * self._pixels(centre)) * (1.25 if corners == 4 else 1.0)
        self._polyline(scene, _circle(centre, radius, corners), rgba, width)

    def _polyline(self, scene, points, rgba, width: float = 1.0) -> None:
        """Lines `width` x RING_WIDTH_PX pixels wide from point to point (unlit, in their exact colour;
        a fraction of what capsules cost on a software GL)."""
        mujoco = self.mujoco
        rgba = np.asarray(rgba, dtype=np.float32)
        for start, end in itertools.pairwise(points):
            if scene.ngeom >= scene.maxgeom:
                return
            geom = scene.geoms[scene.ngeom]
            mujoco.mjv_initGeom(geom, mujoco.mjtGeom.mjGEOM_LINE, _ZERO3, _ZERO3, _EYE9, rgba)
            mujoco.mjv_connector(geom, mujoco.mjtGeom.mjGEOM_LINE, width * RING_WIDTH_PX, start, end)
            scene.ngeom += 1

    def _disc(self, scene, centre, radius, rgba) -> None:
        if scene.ngeom >= scene.maxgeom:
            return
        self.mujoco.mjv_initGeom(
            scene.geoms[scene.ngeom],
            self.mujoco.mjtGeom.mjGEOM_CYLINDER,
            np.array([radius, 0.01, 0.0]),
            np.asarray(centre, dtype=np.float64),
            np.eye(3).ravel(),
            np.asarray(rgba, dtype=np.float32),
        )
        scene.ngeom += 1


def view_box(config: TaskConfig, top: float) -> np.ndarray:
    """[8, 3] corners of what the MuJoCo frames show: the floor out to the arena's edge (game mode:
    out to the target discs, which reach past it), the arena up to height `top` (the obstacles'
    tops), each grown by VIEW_MARGIN."""
    floor = config.arena_half_size
    if config.mode == "cefc":
        floor = max(floor, config.target_corner + config.target_radius)
    walls = config.arena_half_size + VIEW_MARGIN
    floor += VIEW_MARGIN
    return np.array(
        [
            (sx * half, sy * half, z)
            for half, z in ((floor, 0.0), (walls, top))
            for sx in (-1.0, 1.0)
            for sy in (-1.0, 1.0)
        ]
    )


def fit_camera(points, elevation: float, azimuth: float, fovy: float, aspect: float) -> tuple[np.ndarray, float]:
    """(lookat [3], distance) of a MuJoCo free camera at this elevation and azimuth (degrees) that
    holds every point of `points` [P, 3] inside a frame of this aspect ratio (width / height) and
    vertical field of view `fovy` (degrees), as close to them as it can be.

    In the camera's frame (right r, up u, forward f; MuJoCo's free camera: f from azimuth and
    elevation, u perpendicular to it in the vertical plane, r = f x u) a point p is inside iff
    |(p - c).u| <= t (p - c).f and |(p - c).r| <= aspect t (p - c).f, t = tan(fovy / 2): linear
    in the camera position c. The largest c.f they allow is (min(p.u + t p.f) - max(p.u - t p.f)) / 2t,
    and horizontally the same with aspect t; the smaller of the two is the camera's, and c.u, c.r
    sit in the middle of what the constraints leave, so the frame is filled edge to edge in the
    tighter direction and centred in the other. The look-at point is the points' centroid's depth
    along f.
    """
    points = np.asarray(points, dtype=np.float64)
    forward = _forward(elevation, azimuth)
    el, az = math.radians(elevation), math.radians(azimuth)
    up = np.array([-math.sin(el) * math.cos(az), -math.sin(el) * math.sin(az), math.cos(el)])
    right = np.cross(forward, up)
    t_up = math.tan(math.radians(fovy) / 2.0)
    depth = points @ forward
    reach_f, middles = [], []
    for axis, t in ((up, t_up), (right, aspect * t_up)):
        across = points @ axis
        high, low = np.min(across + t * depth), np.max(across - t * depth)
        reach_f.append((high - low) / (2.0 * t))
        middles.append(0.5 * (high + low))
    eye = min(reach_f) * forward + middles[0] * up + middles[1] * right
    distance = float(np.dot(points.mean(axis=0) - eye, forward))
    return eye + distance * forward, distance


def _forward(elevation: float, azimuth: float) -> np.ndarray:
    el, az = math.radians(elevation), math.radians(azimuth)
    return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])


def _circle(centre, radius: float, n: int) -> np.ndarray:
    """[n + 1, 3] a closed horizontal circle around centre (x, y, z)."""
    angle = np.linspace(0.0, 2.0 * np.pi, n + 1)
    return np.stack(
        [centre[0] + radius * np.cos(angle), centre[1] + radius * np.sin(angle), np.full(n + 1, centre[2])], axis=1
    )


def _render_model(world):
    """A copy of env 0's MjModel to draw: rebuilt with the airframe's visual geoms when the world
    left them out (same bodies and qpos, so env 0's state carries over as it is)."""
    from cefc_mj.sim.mujoco_world import MujocoWorld, build_scene

    source = world.models[0]
    if not isinstance(world, MujocoWorld) or world.config.visual_geoms:
        return copy.deepcopy(source)
    model = build_scene(
        dataclasses.replace(world.config, visual_geoms=True),
        world.n_agents,
        world.n_obstacles,
        world.with_adversary,
        world.uav_radius,
        world.obstacle_radius,
        airframe=world.airframe,
    )
    if (model.nq, model.nbody) != (source.nq, source.nbody):
        raise ConfigError("render_mode='rgb_array': the scene with visual geoms does not match the world's bodies")
    return model


def _lighten_floor(mujoco, model, half: float) -> None:
    """Lighten the floor planes' textures (by _FLOOR_LIGHTNESS towards white) and grow the planes to
    3 x `half` so that the frame shows no background; their checker keeps its size."""
    done = set()
    for g in np.flatnonzero(model.geom_type == mujoco.mjtGeom.mjGEOM_PLANE):
        material = model.geom_matid[g]
        if model.geom_size[g, 0] > 0 and model.geom_size[g, 1] > 0:
            grow = max(1.0, 3.0 * half / min(model.geom_size[g, :2]))
            model.geom_size[g, :2] *= grow
            if material >= 0 and not model.mat_texuniform[material]:
                model.mat_texrepeat[material] *= grow
        texture = model.mat_texid[material, mujoco.mjtTextureRole.mjTEXROLE_RGB] if material >= 0 else -1
        if texture >= 0 and texture not in done:
            done.add(texture)
            start = model.tex_adr[texture]
            size = model.tex_height[texture] * model.tex_width[texture] * model.tex_nchannel[texture]
            texels = model.tex_data[start : start + size].astype(np.float64)
            model.tex_data[start : start + size] = np.round(255.0 - (255.0 - texels) * (1.0 - _FLOOR_LIGHTNESS))


def _close_if_alive(ref) -> None:
    frames = ref()
    if frames is not None:
        frames.close()
