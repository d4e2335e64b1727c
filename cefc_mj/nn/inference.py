"""The AT-M actor's deterministic forward as one compiled kernel: what every evaluator flies.

`ATMActor.deterministic_actions` (and so `Policy.act`, `run_episode`, the hierarchy's low level and
the SITL-M agents) computes `to_acceleration(F_o(F_f(o) + F_a(d) - F_a(d_free)))` here, in float32
like the torch module, row by row:

- **Fixed summation order.** Each output of a layer is `b_j + x_0 w_0j + x_1 w_1j + ...`, summed in
  input order with separate multiplies and adds (no fused multiply-add, no BLAS blocking). The loop
  runs over inputs outside and outputs inside, so the compiler vectorises across outputs without
  reordering any sum: the result is the same on every x86/ARM CPU and SIMD width, and a row's
  actions do not depend on the batch it is in (one agent alone, as in a SITL-M process, gets the
  bits the lock-step evaluator gets for it). BLAS (MKL's sgemm, which torch calls) picks its kernel
  by CPU and batch size, which moves the last bits of an action from machine to machine.
- **Speed.** Small batches are all per-call overhead in torch (about twenty operator dispatches);
  here one call: ~20 us for one agent and ~100 us for 8 against ~210 and ~330 us (at 256 rows BLAS
  wins: ~10 against ~8 us a row).
- It agrees with the torch forward to float32 rounding (max |difference| < 1e-5 m/s^2 on the shipped
  policies; `tests/test_eval_speed_equivalence.py` also checks the kernel against numpy doing the
  documented operations one at a time); training keeps the torch module and its gradients.

`InferenceWeights.from_actor` takes float32 copies of the weights, transposed to [in, out]; the
actor rebuilds them when its parameters change (see `ATMActor.inference_weights`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cefc_mj.jit import njit

# tanh as a rational function of float32 arithmetic only (Eigen's `generic_fast_tanh_float`
# coefficients, degree 13/6, clamped at |x| = 7.905): no libm call, so it vectorises and gives the
# same bits everywhere; within 4e-7 of the exact tanh (torch's vectorised tanh: within 0.5 ulp)
_TANH_CLAMP = np.float32(7.90531110763549805)
_TANH_TINY = np.float32(0.0004)
_A1, _A3, _A5, _A7, _A9, _A11, _A13 = (
    np.float32(c)
    for c in (
        4.89352455891786e-03,
        6.37261928875436e-04,
        1.48572235717979e-05,
        5.12229709037114e-08,
        -8.60467152213735e-11,
        2.00018790482477e-13,
        -2.76076847742355e-16,
    )
)
_B0, _B2, _B4, _B6 = (
    np.float32(c) for c in (4.89352518554385e-03, 2.26843463243900e-03, 1.18534705686654e-04, 1.19825839466702e-06)
)


@njit(inline="always")
def tanh32(x):
    """tanh of a float32, to within 4e-7 (see above)."""
    x = min(max(x, -_TANH_CLAMP), _TANH_CLAMP)
    if abs(x) < _TANH_TINY:
        return x
    x2 = x * x
    p = x2 * _A13 + _A11
    p = x2 * p + _A9
    p = x2 * p + _A7
    p = x2 * p + _A5
    p = x2 * p + _A3
    p = x2 * p + _A1
    q = x2 * _B6 + _B4
    q = x2 * q + _B2
    q = x2 * q + _B0
    return x * p / q


@njit(inline="always")
def _dense(x, w, b, tanh, out):
    """out = (tanh)(b + x @ w) for rows x [R, I], w [I, O], b [O], out [R, O] (float32). Every output
    is summed in input order, whatever R: four rows and four inputs per pass over the outputs (the
    same sums, each weight loaded once for four rows, each output stored once per four inputs)."""
    n_rows, n_in = x.shape
    n_out = out.shape[1]
    for r in range(n_rows):
        for j in range(n_out):
            out[r, j] = b[j]
    r = 0
    while r < n_rows:
        if r + 4 <= n_rows:
            o0, o1, o2, o3 = out[r], out[r + 1], out[r + 2], out[r + 3]
            i = 0
            while i + 4 <= n_in:
                w0, w1, w2, w3 = w[i], w[i + 1], w[i + 2], w[i + 3]
                a0, b0, c0, d0 = x[r, i], x[r, i + 1], x[r, i + 2], x[r, i + 3]
                a1, b1, c1, d1 = x[r + 1, i], x[r + 1, i + 1], x[r + 1, i + 2], x[r + 1, i + 3]
                a2, b2, c2, d2 = x[r + 2, i], x[r + 2, i + 1], x[r + 2, i + 2], x[r + 2, i + 3]
                a3, b3, c3, d3 = x[r + 3, i], x[r + 3, i + 1], x[r + 3, i + 2], x[r + 3, i + 3]
                for j in range(n_out):
                    p, q, s, t = w0[j], w1[j], w2[j], w3[j]
                    o0[j] = (((o0[j] + a0 * p) + b0 * q) + c0 * s) + d0 * t
                    o1[j] = (((o1[j] + a1 * p) + b1 * q) + c1 * s) + d1 * t
                    o2[j] = (((o2[j] + a2 * p) + b2 * q) + c2 * s) + d2 * t
                    o3[j] = (((o3[j] + a3 * p) + b3 * q) + c3 * s) + d3 * t
                i += 4
            while i < n_in:
                wi = w[i]
                a0, a1, a2, a3 = x[r, i], x[r + 1, i], x[r + 2, i], x[r + 3, i]
                for j in range(n_out):
                    wij = wi[j]
                    o0[j] += a0 * wij
                    o1[j] += a1 * wij
                    o2[j] += a2 * wij
                    o3[j] += a3 * wij
                i += 1
            r += 4
        else:
            o0 = out[r]
            i = 0
            while i + 4 <= n_in:
                w0, w1, w2, w3 = w[i], w[i + 1], w[i + 2], w[i + 3]
                a0, b0, c0, d0 = x[r, i], x[r, i + 1], x[r, i + 2], x[r, i + 3]
                for j in range(n_out):
                    o0[j] = (((o0[j] + a0 * w0[j]) + b0 * w1[j]) + c0 * w2[j]) + d0 * w3[j]
                i += 4
            while i < n_in:
                wi = w[i]
                a0 = x[r, i]
                for j in range(n_out):
                    o0[j] += a0 * wi[j]
                i += 1
            r += 1
    if tanh:
        for r in range(n_rows):
            for j in range(n_out):
                out[r, j] = tanh32(out[r, j])


@njit(inline="always")
def _mlp3(x, layers, tanh_last, h0, h1, out):
    _dense(x, layers[0], layers[1], True, h0)
    _dense(h0, layers[2], layers[3], True, h1)
    _dense(h1, layers[4], layers[5], tanh_last, out)


@njit
def atm_forward(
    obs,
    formation_index,
    lidar_lo,
    lidar_hi,
    safe,
    lidar_range,
    safe_margin,
    formation,
    obstacle,
    output,
    free,
    velocity_lo,
    velocity_gain,
    accel_max,
    actions,
):
    """actions [R, A] for observations obs [R, D] (float32). formation / obstacle / output are
    (w0, b0, w1, b1, w2, b2) tuples of a 3-layer MLP; free = F_a(d_free) [H]; velocity_lo < 0 means
    the head outputs accelerations, otherwise velocity_gain * (head - obs[velocity_lo:+A])."""
    n_rows = obs.shape[0]
    hidden = free.shape[0]
    n_act = actions.shape[1]
    x_f = np.empty((n_rows, formation_index.shape[0]), dtype=np.float32)
    x_a = np.empty((n_rows, lidar_hi - lidar_lo), dtype=np.float32)
    h0 = np.empty((n_rows, hidden), dtype=np.float32)
    h1 = np.empty((n_rows, hidden), dtype=np.float32)
    f = np.empty((n_rows, hidden), dtype=np.float32)
    a = np.empty((n_rows, hidden), dtype=np.float32)
    head = np.empty((n_rows, n_act), dtype=np.float32)
    threshold = np.float32(lidar_range - 1e-6)
    margin = np.float32(safe_margin)
    gain = np.float32(velocity_gain)
    limit = np.float32(accel_max)
    for r in range(n_rows):
        for k in range(formation_index.shape[0]):
            x_f[r, k] = obs[r, formation_index[k]]
        for k in range(lidar_hi - lidar_lo):
            d = obs[r, lidar_lo + k]
            x_a[r, k] = d - margin if safe and d < threshold else d
    _mlp3(x_f, formation, True, h0, h1, f)
    _mlp3(x_a, obstacle, True, h0, h1, a)
    for r in range(n_rows):
        for j in range(hidden):
            f[r, j] += a[r, j] - free[j]
    _mlp3(f, output, False, h0, h1, head)
    for r in range(n_rows):
        for j in range(n_act):
            u = head[r, j]
            if velocity_lo >= 0:
                u = gain * (u - obs[r, velocity_lo + j])
            actions[r, j] = min(max(u, -limit), limit)


@njit
def mlp3_forward(x, layers, tanh_last, out):
    """A 3-layer MLP (tanh between layers) on rows x [R, I] -> out [R, O]."""
    hidden = layers[1].shape[0]
    _mlp3(
        x,
        layers,
        tanh_last,
        np.empty((x.shape[0], hidden), dtype=np.float32),
        np.empty((x.shape[0], hidden), dtype=np.float32),
        out,
    )


@dataclass(frozen=True)
class InferenceWeights:
    """The arrays `atm_forward` reads, for one actor (float32, weights as [in, out])."""

    formation: tuple
    obstacle: tuple
    output: tuple
    free: np.ndarray
    formation_index: np.ndarray
    lidar: tuple[int, int]
    safe: bool
    lidar_range: float
    safe_margin: float
    velocity_lo: int
    velocity_gain: float
    accel_max: float
    act_dim: int

    @classmethod
    def from_actor(cls, actor) -> "InferenceWeights":
        """Copies of an ATMActor's weights (detached; later updates need a new instance)."""
        import torch

        def layers(seq) -> tuple:
            linears = [m for m in seq if isinstance(m, torch.nn.Linear)]
            if len(linears) != 3:
                raise ValueError(f"atm_forward runs 3-layer MLPs, got {len(linears)} layers")
            out = []
            for m in linears:
                out += [
                    np.ascontiguousarray(m.weight.detach().cpu().numpy().T, dtype=np.float32),
                    np.ascontiguousarray(m.bias.detach().cpu().numpy(), dtype=np.float32),
                ]
            return tuple(out)

        cfg = actor.cfg
        velocity = actor.velocity_slice
        weights = cls(
            formation=layers(actor.formation),
            obstacle=layers(actor.obstacle),
            output=layers(actor.output),
            free=np.zeros(cfg.hidden, dtype=np.float32),
            formation_index=actor.formation_index.cpu().numpy().astype(np.int64),
            lidar=(actor.lidar_slice.start, actor.lidar_slice.stop),
            safe=bool(cfg.safe),
            lidar_range=float(cfg.lidar_range),
            safe_margin=float(cfg.safe_margin),
            velocity_lo=velocity.start if cfg.action == "velocity" else -1,
            velocity_gain=float(cfg.velocity_gain),
            accel_max=float(cfg.accel_max),
            act_dim=cfg.act_dim,
        )
        # F_a(d_free) by the same kernel, so that a drone whose beams all read the range gets a - free = 0 exactly
        free_lidar = np.full((1, weights.lidar[1] - weights.lidar[0]), cfg.lidar_range, dtype=np.float32)
        mlp3_forward(free_lidar, weights.obstacle, True, weights.free[None])
        return weights

    def actions(self, obs: np.ndarray) -> np.ndarray:
        """float32 actions [..., A] for observations [..., D]."""
        obs = np.asarray(obs)
        rows = np.ascontiguousarray(obs.reshape(-1, obs.shape[-1]), dtype=np.float32)
        out = np.empty((rows.shape[0], self.act_dim), dtype=np.float32)
        atm_forward(
            rows,
            self.formation_index,
            self.lidar[0],
            self.lidar[1],
            self.safe,
            self.lidar_range,
            self.safe_margin,
            self.formation,
            self.obstacle,
            self.output,
            self.free,
            self.velocity_lo,
            self.velocity_gain,
            self.accel_max,
            out,
        )
        return out.reshape(obs.shape[:-1] + (self.act_dim,))
