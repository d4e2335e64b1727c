"""ConsMAC's supervised step (eq. (11)) with a hand-written backward pass: the training hot loop.

`supervised_grads(net, batch)` computes the loss of `ConsMAC.supervised_loss` on a replay batch and
writes every parameter's gradient into `.grad`, as `loss.backward()` would after a `zero_grad()`,
without autograd. It is the same arithmetic in another order, so the gradients agree with autograd's
to float rounding (about 1e-6 relative; tests/test_consmac_grad.py). What it saves, per step of
2,048 rows on one core (docs/research/highlevel_speed.md):

- no autograd graph, and no gradient that nothing reads: the memory's, the attention's and the
  estimator's input gradients stop where the input is data (the replay's observation, own message
  and received messages), and the keys' gradient is taken for the distance code only;
- the query's distance code Phi(0) is the same row for every agent, so its part of the query
  projection is one row, added as a bias (its gradient through the frequencies is exactly zero:
  d cos(w 0) / dw = 0);
- the attention with one query per row runs on the reassociated products of
  `MaskedMultiHeadAttention(fast=True)`: the per-head projections W_K,h^T q_h and W_V,h (pooled) as
  torch matrix products, head-major, and the scores, the masked softmax, the pooled keys and their
  gradients in two numba kernels that read open inbox slots only (the contractions over at most 7
  slots are too small for batched matrix products to run well on a CPU); the keys stay as their two
  halves, received messages and distance codes, never concatenated, and the distance code (cos, and
  sin in the backward pass) is computed on open slots only.

`fused_supported(net)` says which modules it covers: ConsMAC (message_content "learned") with the
residual LayerNorm message, every Fig. 7 ablation included; anything else keeps autograd.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from cefc_mj.jit import njit
from cefc_mj.nn.consmac import ConsMAC


def fused_supported(net: torch.nn.Module) -> bool:
    """True when `supervised_grads` covers this module (otherwise train it with autograd)."""
    return isinstance(net, ConsMAC) and net.cfg.residual and net.cfg.message_content == "learned"


@torch.no_grad()
def supervised_grads(net: ConsMAC, batch: dict[str, torch.Tensor]) -> torch.Tensor:
    """Eq. (11) on `batch` (obs, own, messages, mask, distance, label; each [L, ...]) and its gradient
    in every parameter's `.grad` (replaced, not accumulated; None where autograd leaves none: the
    distance frequencies under wo-de). Returns the loss, a 0-d tensor without a graph."""
    cfg = net.cfg
    obs, own, messages, mask, distance, label = (
        batch[k] for k in ("obs", "own", "messages", "mask", "distance", "label")
    )
    n_rows, k = mask.shape
    dtype = net.distance_encoder.frequency.weight.dtype
    ablation = cfg.ablation
    d, dist_dim, sent = cfg.message_dim, cfg.distance_dim, cfg.sent_dim
    h_count, hd = cfg.n_heads, cfg.attention_dim // cfg.n_heads
    att, gru, norm = net.attention, net.memory, net.norm
    lin1, lin2, lin3 = net.estimator[0], net.estimator[2], net.estimator[4]
    freq = net.distance_encoder.frequency.weight.view(-1)  # w [D]
    scale_d = 1.0 / math.sqrt(dist_dim)

    # ---------------------------------------------------------------- forward
    mask = mask.to(torch.bool)
    if ablation == "wo-com":
        mask = torch.zeros_like(mask)
    o = obs.to(dtype).index_select(-1, net.local_index) * cfg.obs_scale
    if ablation == "wo-mem":
        hidden = torch.zeros(n_rows, d, dtype=dtype)
    else:
        hidden = own.to(dtype)
        if sent < d:  # ConsMAC-G
            hidden = torch.nn.functional.pad(hidden, (0, d - sent))
    gi = torch.addmm(gru.bias_ih, o, gru.weight_ih.t())  # [L, 3d]: r, z, n
    gh = torch.addmm(gru.bias_hh, hidden, gru.weight_hh.t())
    gates = torch.sigmoid(gi[:, : 2 * d] + gh[:, : 2 * d])
    r, z = gates[:, :d], gates[:, d:]
    gh_n = gh[:, 2 * d :]
    n = torch.tanh(torch.addcmul(gi[:, 2 * d :], r, gh_n))
    memory = torch.addcmul(n, z, hidden - n)  # eq. (7), (1 - z) n + z h

    wq = att.query.weight  # [A, d + D]
    query_code = None if ablation == "wo-de" else torch.full((dist_dim,), scale_d, dtype=dtype)  # Phi(0)
    q_bias = att.query.bias if query_code is None else att.query.bias + wq[:, d:] @ query_code
    q = torch.addmm(q_bias, memory, wq[:, :d].t())  # [L, A]
    q_heads = q.view(n_rows, h_count, hd)

    # E_m-i = [m_ij || Phi_dj] (eq. (8)) is kept as its two halves, the received messages and the
    # distance codes, each zero on empty slots, so that no concatenated copy is made and the
    # backward pass reaches the codes alone.
    sent_keys = messages.to(dtype).contiguous()  # [L, K, sent]; the kernels never read an empty slot
    open_index = None
    if ablation == "wo-de":
        code = torch.zeros(n_rows, k, dist_dim, dtype=dtype)
    else:  # Phi_d on the open slots only (cos and its derivative are the step's costliest elementwise ops)
        open_index = mask.reshape(-1).nonzero().squeeze(-1)
        open_distance = distance.reshape(-1).to(dtype).index_select(0, open_index)
        cos_arg = open_distance.unsqueeze(-1) * freq  # [open, D]
        code = torch.empty(n_rows * k, dist_dim, dtype=dtype)
        code.index_copy_(0, open_index, torch.cos(cos_arg) * scale_d)
        code = code.view(n_rows, k, dist_dim)  # Phi_d, on the open slots (the others are never read)

    inv_sqrt_hd = np.float32(1.0 / math.sqrt(hd))
    q_h = q.view(n_rows, h_count, hd).transpose(0, 1)  # [H, L, hd]
    w_key = att.key.weight.view(h_count, hd, sent + dist_dim)
    w_key_sent, w_key_code = w_key[..., :sent], w_key[..., sent:]
    q_key_sent = torch.bmm(q_h, w_key_sent)  # [H, L, sent]: W_K,h^T q_h, the message half
    q_key_code = torch.bmm(q_h, w_key_code)  # [H, L, D]
    key_bias = (q_heads * att.key.bias.view(h_count, hd)).sum(-1)  # [L, H]
    weights = torch.empty(n_rows, h_count, k, dtype=dtype)
    pooled_sent = torch.empty(h_count, n_rows, sent, dtype=dtype)  # head-major, as the projections take it
    pooled_code = torch.empty(h_count, n_rows, dist_dim, dtype=dtype)
    mask_np = mask.numpy()
    _attend(
        q_key_sent.numpy(),
        q_key_code.numpy(),
        sent_keys.numpy(),
        code.numpy(),
        key_bias.numpy(),
        mask_np,
        inv_sqrt_hd,
        weights.numpy(),
        pooled_sent.numpy(),
        pooled_code.numpy(),
    )
    weight_sum = weights.sum(-1, keepdim=True)  # [L, H, 1]
    w_value = att.value.weight.view(h_count, hd, sent + dist_dim)
    w_value_sent, w_value_code = w_value[..., :sent], w_value[..., sent:]
    heads = torch.bmm(pooled_sent, w_value_sent.transpose(1, 2))
    heads += torch.bmm(pooled_code, w_value_code.transpose(1, 2))  # [H, L, hd]
    heads = (heads.transpose(0, 1) + weight_sum * att.value.bias.view(h_count, hd)).reshape(n_rows, h_count * hd)
    has_neighbour = mask.any(dim=-1, keepdim=True).to(dtype)  # [L, 1]
    attended = torch.addmm(att.out.bias, heads, att.out.weight.t()) * has_neighbour

    x = memory + attended
    message, ln_mean, ln_rstd = torch.native_layer_norm(x, (d,), norm.weight, norm.bias, norm.eps)  # eq. (9)

    a1 = torch.tanh(torch.addmm(lin1.bias, message, lin1.weight.t()))
    a2 = torch.tanh(torch.addmm(lin2.bias, a1, lin2.weight.t()))
    estimate = torch.addmm(lin3.bias, a2, lin3.weight.t())  # eq. (10)
    error = estimate - label.to(dtype)
    loss = (error * error).sum(-1).mean()  # eq. (11)

    # ---------------------------------------------------------------- backward
    grads: dict[torch.Tensor, torch.Tensor | None] = {}
    d_est = error * (2.0 / n_rows)
    grads[lin3.weight], grads[lin3.bias] = d_est.t() @ a2, d_est.sum(0)
    d_z2 = torch.ops.aten.tanh_backward(d_est @ lin3.weight, a2)
    grads[lin2.weight], grads[lin2.bias] = d_z2.t() @ a1, d_z2.sum(0)
    d_z1 = torch.ops.aten.tanh_backward(d_z2 @ lin2.weight, a1)
    grads[lin1.weight], grads[lin1.bias] = d_z1.t() @ message, d_z1.sum(0)
    d_message = d_z1 @ lin1.weight
    d_x, grads[norm.weight], grads[norm.bias] = torch.ops.aten.native_layer_norm_backward(
        d_message, x, (d,), ln_mean, ln_rstd, norm.weight, norm.bias, (True, True, True)
    )

    d_att = d_x * has_neighbour  # [L, d]
    grads[att.out.weight], grads[att.out.bias] = d_att.t() @ heads, d_att.sum(0)
    d_heads = (d_att @ att.out.weight).view(n_rows, h_count, hd)
    d_heads_h = d_heads.transpose(0, 1)  # [H, L, hd]
    grads[att.value.weight] = torch.cat(
        [torch.bmm(d_heads_h.transpose(1, 2), pooled_sent), torch.bmm(d_heads_h.transpose(1, 2), pooled_code)], dim=-1
    ).reshape(-1, sent + dist_dim)
    grads[att.value.bias] = (d_heads * weight_sum).sum(0).reshape(-1)
    d_pooled_sent = torch.bmm(d_heads_h, w_value_sent)  # [H, L, sent]
    d_pooled_code = torch.bmm(d_heads_h, w_value_code)  # [H, L, D]
    d_value_bias = (d_heads * att.value.bias.view(h_count, hd)).sum(-1)  # [L, H]: d weight_sum
    d_q_key_sent = torch.empty(h_count, n_rows, sent, dtype=dtype)
    d_q_key_code = torch.empty(h_count, n_rows, dist_dim, dtype=dtype)
    d_key_bias = torch.empty(n_rows, h_count, dtype=dtype)
    d_code = torch.empty(n_rows, k, dist_dim, dtype=dtype)  # written on the open slots
    _attend_backward(
        q_key_code.numpy(),
        sent_keys.numpy(),
        code.numpy(),
        weights.numpy(),
        d_pooled_sent.numpy(),
        d_pooled_code.numpy(),
        d_value_bias.numpy(),
        mask_np,
        inv_sqrt_hd,
        d_q_key_sent.numpy(),
        d_q_key_code.numpy(),
        d_key_bias.numpy(),
        d_code.numpy(),
    )
    q_h_t = q_h.transpose(1, 2)  # [H, hd, L]
    grads[att.key.weight] = torch.cat([torch.bmm(q_h_t, d_q_key_sent), torch.bmm(q_h_t, d_q_key_code)], dim=-1).reshape(
        -1, sent + dist_dim
    )
    grads[att.key.bias] = (d_key_bias.unsqueeze(-1) * q_heads).sum(0).reshape(-1)
    d_q = torch.bmm(d_q_key_sent, w_key_sent.transpose(1, 2))
    d_q += torch.bmm(d_q_key_code, w_key_code.transpose(1, 2))  # [H, L, hd]
    d_q = (d_q.transpose(0, 1) + d_key_bias.unsqueeze(-1) * att.key.bias.view(h_count, hd)).reshape(n_rows, -1)

    if open_index is None:  # wo-de: the codes are constants, the frequencies get no gradient
        grads[net.distance_encoder.frequency.weight] = None
    else:  # of the keys, only the distance codes depend on a parameter
        d_open = d_code.view(n_rows * k, dist_dim).index_select(0, open_index)
        d_open *= torch.sin(cos_arg)
        d_open *= (open_distance * -scale_d).unsqueeze(-1)
        grads[net.distance_encoder.frequency.weight] = d_open.sum(0).view(-1, 1)

    d_q_sum = d_q.sum(0)
    grad_wq = torch.empty_like(wq)
    grad_wq[:, :d] = d_q.t() @ memory
    if query_code is None:
        grad_wq[:, d:] = 0.0
    else:
        grad_wq[:, d:] = torch.outer(d_q_sum, query_code)
    grads[wq], grads[att.query.bias] = grad_wq, d_q_sum

    d_memory = torch.addmm(d_x, d_q, wq[:, :d])
    d_n = torch.ops.aten.tanh_backward(d_memory - d_memory * z, n)  # d (gi_n + r gh_n)
    d_gates = torch.cat([d_n * gh_n, d_memory * (hidden - n)], dim=-1)  # d r, d z
    d_gates = torch.ops.aten.sigmoid_backward(d_gates, gates)
    d_gi = torch.cat([d_gates, d_n], dim=-1)
    d_gh = torch.cat([d_gates, d_n * r], dim=-1)
    grads[gru.weight_ih], grads[gru.bias_ih] = d_gi.t() @ o, d_gi.sum(0)
    grads[gru.weight_hh], grads[gru.bias_hh] = d_gh.t() @ hidden, d_gh.sum(0)

    for p in net.parameters():
        g = grads.get(p, "missing")
        if isinstance(g, str):
            raise RuntimeError(f"supervised_grads: no gradient for a parameter of shape {tuple(p.shape)}")
        p.grad = None if g is None else g.view_as(p)
    return loss


# ---------------------------------------------------------------------------- compiled kernels
# Per row l and head h, one query against the row's K keys, each key in two halves (the message and
# the distance code); only open slots are read. The query products, pooled keys and their gradients
# are head-major, [H, L, .], as the per-head projections make and take them. The contractions are
# over K <= 7 slots and the key widths, too small for batched matrix products to run well on a CPU.
_FAST = {"reassoc", "contract", "nsz"}  # reorder sums (SIMD), fuse multiply-adds; no NaN/inf assumptions


@njit(fastmath=_FAST)
def _attend(q_sent, q_code, k_sent, k_code, key_bias, mask, scale, weights, pooled_sent, pooled_code):
    """scores = (q . e_j + q . b_K) * scale on the open slots, weights = their softmax (zero on empty
    slots and where none is open), pooled = sum_j weights_j e_j (both halves)."""
    n_heads, n_rows, n_sent = q_sent.shape
    n_slots, n_code = mask.shape[1], q_code.shape[2]
    scores = np.empty(n_slots, dtype=np.float32)
    for row in range(n_rows):
        for head in range(n_heads):
            top = -np.inf
            for slot in range(n_slots):
                weights[row, head, slot] = 0.0
                if mask[row, slot]:
                    acc = np.float32(0.0)
                    for e in range(n_sent):
                        acc += q_sent[head, row, e] * k_sent[row, slot, e]
                    for e in range(n_code):
                        acc += q_code[head, row, e] * k_code[row, slot, e]
                    scores[slot] = (acc + key_bias[row, head]) * scale
                    top = max(top, scores[slot])
            for e in range(n_sent):
                pooled_sent[head, row, e] = 0.0
            for e in range(n_code):
                pooled_code[head, row, e] = 0.0
            if top == -np.inf:
                continue
            total = np.float32(0.0)
            for slot in range(n_slots):
                if mask[row, slot]:
                    scores[slot] = np.exp(scores[slot] - top)
                    total += scores[slot]
            for slot in range(n_slots):
                if mask[row, slot]:
                    w = scores[slot] / total
                    weights[row, head, slot] = w
                    for e in range(n_sent):
                        pooled_sent[head, row, e] += w * k_sent[row, slot, e]
                    for e in range(n_code):
                        pooled_code[head, row, e] += w * k_code[row, slot, e]


@njit(fastmath=_FAST)
def _attend_backward(
    q_code,
    k_sent,
    k_code,
    weights,
    d_pooled_sent,
    d_pooled_code,
    d_weight_sum,
    mask,
    scale,
    d_q_sent,
    d_q_code,
    d_key_bias,
    d_code,
):
    """The gradient of `_attend` (with `weight_sum` = sum_j weights_j, whose gradient is
    d_weight_sum) with respect to the query products q_sent, q_code, the key bias term and the
    distance codes (written on the open slots only)."""
    n_heads, n_rows, n_sent = d_pooled_sent.shape
    n_slots, n_code = mask.shape[1], q_code.shape[2]
    d_scores = np.empty(n_slots, dtype=np.float32)
    for row in range(n_rows):
        for slot in range(n_slots):
            if mask[row, slot]:
                for e in range(n_code):
                    d_code[row, slot, e] = 0.0
        for head in range(n_heads):
            inner = np.float32(0.0)
            for slot in range(n_slots):
                d_scores[slot] = 0.0
                if mask[row, slot]:
                    acc = np.float32(0.0)
                    for e in range(n_sent):
                        acc += d_pooled_sent[head, row, e] * k_sent[row, slot, e]
                    for e in range(n_code):
                        acc += d_pooled_code[head, row, e] * k_code[row, slot, e]
                    d_scores[slot] = acc + d_weight_sum[row, head]  # d weights_j
                    inner += weights[row, head, slot] * d_scores[slot]
            bias = np.float32(0.0)
            for e in range(n_sent):
                d_q_sent[head, row, e] = 0.0
            for e in range(n_code):
                d_q_code[head, row, e] = 0.0
            for slot in range(n_slots):
                if mask[row, slot]:
                    w = weights[row, head, slot]
                    ds = w * (d_scores[slot] - inner) * scale  # softmax, then the score's scale
                    bias += ds
                    for e in range(n_sent):
                        d_q_sent[head, row, e] += ds * k_sent[row, slot, e]
                    for e in range(n_code):
                        d_q_code[head, row, e] += ds * k_code[row, slot, e]
                        d_code[row, slot, e] += w * d_pooled_code[head, row, e] + ds * q_code[head, row, e]
            d_key_bias[row, head] = bias
