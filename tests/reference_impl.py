"""Slow, obvious numpy references of the compiled hot-loop kernels (cefc_mj/task/kernels.py)."""

import numpy as np

from cefc_mj.task.formation import directed_hausdorff, formation_template


def connected_groups_reference(positions: np.ndarray, radius: float) -> np.ndarray:
    """Connected components of the graph "distance < radius" per env.

    positions [B, N, 2] -> labels [B, N] int, each component labelled by its smallest member index
    (so labels are stable and comparable across steps).
    """
    b, n, _ = positions.shape
    diff = positions[:, :, None, :] - positions[:, None, :, :]
    adjacency = np.einsum("bijk,bijk->bij", diff, diff) < radius * radius
    labels = np.broadcast_to(np.arange(n), (b, n)).copy()
    # Min-label propagation over the adjacency: converges in at most n - 1 rounds.
    for _ in range(max(n - 1, 0)):
        candidate = np.where(adjacency, labels[:, None, :], n).min(axis=-1)
        if np.array_equal(candidate, labels):
            break
        labels = candidate
    return labels


def group_formation_error_reference(
    positions: np.ndarray, labels: np.ndarray, spacing: float = 1.0, min_size: int = 3
) -> tuple[np.ndarray, np.ndarray]:
    """Per-group Hausdorff formation error.

    positions [B, N, 2], labels [B, N] (from `connected_groups`, or all zeros for "one group").
    Returns (error [B, N], group_size [B, N]): error[b, g] is HD(Delta_{n_g}, P_g) for the group
    labelled g (indexed by its label), NaN where label g is unused or the group has fewer than
    `min_size` members; group_size[b, g] is that group's size (0 where unused).
    """
    b, n, _ = positions.shape
    one_hot = labels[:, None, :] == np.arange(n)[None, :, None]  # [B, G=N, N]
    size = one_hot.sum(axis=-1)
    centre = np.einsum("bgn,bnk->bgk", one_hot, positions) / np.maximum(size, 1)[..., None]
    centred = positions[:, None, :, :] - centre[:, :, None, :]  # [B, G, N, 2]
    error = np.full((b, n), np.nan)
    for c in np.unique(size):
        if c < min_size:
            continue
        sel = size == c
        error[sel] = directed_hausdorff(formation_template(int(c), spacing)[None], centred[sel], one_hot[sel])
    return error, size


def neighbour_features_reference(
    perceived_pos: np.ndarray, velocity: np.ndarray, slots: int, observation_distance: float
) -> tuple[np.ndarray, np.ndarray]:
    """Neighbours sorted by perceived distance, nearest first, padded to `slots`.

    perceived_pos, velocity [B, N, 2] -> (features [B, N, slots, 4] = (p_j - p_i, v_j - v_i),
    mask [B, N, slots] float, 1 for a neighbour closer than observation_distance).
    """
    b, n, _ = perceived_pos.shape
    rel_pos = perceived_pos[:, None, :, :] - perceived_pos[:, :, None, :]  # [B, i, j, 2]
    rel_vel = velocity[:, None, :, :] - velocity[:, :, None, :]
    dist = np.sqrt((rel_pos * rel_pos).sum(-1))
    dist[:, np.arange(n), np.arange(n)] = np.inf
    take = min(slots, n - 1)
    order = np.argsort(dist, axis=-1, kind="stable")[:, :, :take]  # [B, N, take]
    near = np.take_along_axis(dist, order, axis=-1) < observation_distance
    feats = (
        np.concatenate(
            [
                np.take_along_axis(rel_pos, order[..., None], axis=2),
                np.take_along_axis(rel_vel, order[..., None], axis=2),
            ],
            axis=-1,
        )
        * near[..., None]
    )
    features = np.zeros((b, n, slots, 4))
    mask = np.zeros((b, n, slots))
    features[:, :, :take] = feats
    mask[:, :, :take] = near
    return features, mask


def low_level_observation_reference(
    perceived_pos: np.ndarray,
    velocity: np.ndarray,
    anchor: np.ndarray,
    lidar: np.ndarray,
    slots: int,
    observation_distance: float,
) -> np.ndarray:
    """The low-level observation [B, N, D] float32 as the concatenation of its parts (anchor [B, 2] or [B, N, 2])."""
    from cefc_mj.task.observation import neighbour_features

    b, n, _ = perceived_pos.shape
    if anchor.ndim == 2:
        anchor = anchor[:, None, :]
    feats, mask = neighbour_features(perceived_pos, velocity, slots, observation_distance)
    return np.concatenate([anchor - perceived_pos, velocity, feats.reshape(b, n, -1), mask, lidar], axis=-1).astype(
        np.float32
    )


# ---------------------------------------------------------------------------- ConsMAC's supervised step
def consmac_supervised_loss_reference(net, batch):
    """Eq. (11) on a replay batch as `ConsMAC.supervised_loss` computed it before the hand-written
    backward pass (`cefc_mj/nn/consmac_grad.py`): a frozen copy of `ConsMAC.forward` with the
    reassociated attention (`fast=True`), differentiated by autograd. The speed benchmark and the
    equivalence tests compare the new step against this one."""
    import math

    import torch

    cfg, att = net.cfg, net.attention
    obs, own, messages, mask, distance = (batch[k] for k in ("obs", "own", "messages", "mask", "distance"))
    rows, k = mask.shape
    dtype = net.distance_encoder.frequency.weight.dtype
    mask = mask.to(torch.bool)
    if cfg.ablation == "wo-com":
        mask = torch.zeros_like(mask)
    o = obs.index_select(-1, net.local_index) * cfg.obs_scale
    hidden = own.reshape(rows, cfg.sent_dim)
    if cfg.ablation == "wo-mem":
        hidden = torch.zeros(rows, cfg.message_dim, dtype=dtype)
    elif cfg.sent_dim < cfg.message_dim:
        hidden = torch.nn.functional.pad(hidden, (0, cfg.message_dim - cfg.sent_dim))
    memory = net.memory(o, hidden)
    query_code = net.distance_encoder(memory.new_zeros(rows))
    key_code = net.distance_encoder(distance)
    if cfg.ablation == "wo-de":
        query_code, key_code = torch.zeros_like(query_code), torch.zeros_like(key_code)
    query = torch.cat([memory, query_code], dim=-1)
    keys = torch.cat([messages, key_code], dim=-1)
    # MaskedMultiHeadAttention(fast=True)
    h, hd = att.n_heads, att.head_dim
    keys = keys.masked_fill(~mask.unsqueeze(-1), 0.0)
    has_neighbour = mask.any(dim=-1, keepdim=True)
    open_slot = mask.unsqueeze(1)
    q = att.query(query).view(rows, h, hd)
    w_key = att.key.weight.view(h, hd, keys.shape[-1])
    q_key = (q.transpose(0, 1) @ w_key).transpose(0, 1)
    scores = (q_key @ keys.transpose(1, 2) + (q * att.key.bias.view(h, hd)).sum(-1, keepdim=True)) / math.sqrt(hd)
    scores = scores.masked_fill(~open_slot, torch.finfo(scores.dtype).min)
    weights = torch.softmax(scores, dim=-1) * open_slot
    w_value = att.value.weight.view(h, hd, -1).transpose(1, 2)
    pooled = weights @ keys
    heads = (pooled.transpose(0, 1) @ w_value).transpose(0, 1)
    heads = (heads + weights.sum(-1, keepdim=True) * att.value.bias.view(h, hd)).reshape(rows, h * hd)
    attended = att.out(heads) * has_neighbour
    message = net.norm(memory + attended)
    estimate = net.estimator(message)
    return ((estimate - batch["label"]) ** 2).sum(dim=-1).mean()


def consmac_train_step_reference(net, opt, replay_data, size, batch, generator, max_grad_norm):
    """One step of `HighLevelTrainer.train_consmac` before the speed-up: the replay draw by advanced
    indexing, the autograd loss above, zero_grad, backward, clip and Adam. Returns the loss."""
    import torch

    index = torch.randint(0, size, (batch,), generator=generator)
    rows = {name: tensor[index] for name, tensor in replay_data.items()}
    loss = consmac_supervised_loss_reference(net, rows)
    opt.zero_grad()
    loss.backward()
    torch.nn.utils.clip_grad_norm_(net.parameters(), max_grad_norm)
    opt.step()
    return loss.item()
