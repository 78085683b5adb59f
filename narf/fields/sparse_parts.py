"""Fast path of the masked concatenation of NARF_D / NARF_H, exact against the dense reference.

The dense models feed [p_i gamma(u_i)] (P*60 wide) to one linear layer, but p_i = 0 for every part whose box
does not contain the sample, and a sample lies in only a few boxes. Since W [p_i gamma(u_i)]_i =
sum_i p_i W_i gamma(u_i) (W_i the column block of part i), the fast path evaluates gamma(u_i), the selector and
W_i gamma(u_i) only for in-box (sample, part) pairs, one small matmul per part. The colour blocks depend only on
the ray (xi_i, d_i), so W_k [p_i Y_i] = sum_i p_i (W_k,i Y_i) is a p-weighted sum of a per-ray (P, H/2) table: the
(S, P) weights of a ray's samples times its table.
"""

from __future__ import annotations

import math

import torch


def segment_softmax(logits: torch.Tensor, segments: torch.Tensor, n_segments: int) -> torch.Tensor:
    """Softmax of ``logits`` (M,) within each segment (``segments`` (M,) in [0, n_segments))."""
    peak = torch.full((n_segments,), float("-inf"), dtype=logits.dtype, device=logits.device)
    peak = peak.scatter_reduce(0, segments, logits.detach(), reduce="amax")
    exp = torch.exp(logits - peak.index_select(0, segments))
    total = torch.zeros(n_segments, dtype=logits.dtype, device=logits.device).index_add(0, segments, exp)
    # index_select rather than total[segments]: its gradient is an index_add, not advanced indexing's sort
    return exp / total.index_select(0, segments)


def matmul_dtype(reference: torch.Tensor) -> torch.dtype:
    """The dtype in which autocast runs matmuls on ``reference``'s device (bf16 under ``train.precision=bf16``), or
    ``reference``'s own dtype outside autocast.

    The per-part loops below cast each operand once for all parts with it: under autocast each per-part matmul would
    otherwise cast its slice of the weights, its block of inputs and its bias again (19 copies of each, and as many
    in the backward pass), the same values in many more kernels (docs/results/benchmark.md, *autocast's casts in
    the per-part loops*).
    """
    device = reference.device.type
    return torch.get_autocast_dtype(device) if torch.is_autocast_enabled(device) else reference.dtype


def in_box_pairs(in_box: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The (ray, sample, part) index triples of in-box pairs, sorted by part (stably), so that each part's pairs are
    one contiguous block: in_box (R, S, P) bool -> ray, sample, part, each (M,) long."""
    part, ray, sample = in_box.permute(2, 0, 1).nonzero().unbind(-1)  # row-major over (part, ray, sample): no sort
    return ray, sample, part


def selector_logits(selector, chunks: tuple[torch.Tensor, ...], ray: torch.Tensor, part: torch.Tensor, encoded_zeta):
    """The part selector's logits o_i (narf.fields.selector) of in-box pairs only.

    Each part's rows are one block (the pairs are sorted by part), so its own weights W_i, b_i, w_i, b'_i are
    applied to the block by a matmul rather than gathered per pair: a gathered (M, hidden) copy of 19 rows would
    take, in the backward pass, a sum over every pair of a part into one row (on a GPU, serial per row).

    Args:
        selector: a PartSelector. chunks: per part k, the gamma(u_k) (M_k, 60) of its in-box pairs, in part order.
        ray, part: (M,) of the same pairs, sorted by part. encoded_zeta: (R, 1, 152).

    Returns:
        (M,) logits.
    """
    r_count, p_count = encoded_zeta.shape[0], len(chunks)
    bones = selector.bones(encoded_zeta.reshape(1, r_count, -1)).reshape(r_count * p_count, selector.hidden)
    per_pair = bones.index_select(0, ray * p_count + part).split([len(chunk) for chunk in chunks])
    compute = matmul_dtype(encoded_zeta)  # each operand cast once for every part (see matmul_dtype)
    weights = selector.local.effective_weight().to(compute).unbind(0)
    biases = selector.local.bias.to(compute).unbind(0)
    out_weights = selector.out.effective_weight()[:, 0, :].to(compute).unbind(0)
    out_biases = selector.out.bias[:, 0].unbind(0)  # added in its own dtype, as autocast leaves an addition
    logits = [
        torch.relu(torch.addmm(bias, chunk, weight.T) + bone) @ out_weight + out_bias  # (M_k,), also for M_k = 0
        for chunk, bone, weight, bias, out_weight, out_bias in zip(
            chunks, per_pair, weights, biases, out_weights, out_biases
        )
    ]
    return torch.cat(logits)


def sparse_density_inputs(model, u: torch.Tensor, in_box: torch.Tensor, encoded_zeta: torch.Tensor) -> torch.Tensor:
    """The density input of :func:`sparse_masked_inputs` alone (arguments as there): (1, R, S, H)."""
    r_count, s_count = u.shape[:2]
    return _in_box_density(model, u, in_box, encoded_zeta)[0].reshape(1, r_count, s_count, -1)


def sparse_masked_inputs(
    model, u: torch.Tensor, in_box: torch.Tensor, d_local: torch.Tensor, pose, encoded_zeta: torch.Tensor
):
    """Embedded density and colour inputs of NARF_D / NARF_H without the out-of-box zeros.

    Args:
        model: a NarfH or NarfD (``selector_kind`` and ``selector`` are read when present).
        u: (R, S, P, 3) box coordinates. in_box: (R, S, P). d_local: (R, P, 3). encoded_zeta: (R, 1, 152).

    Returns:
        density (1, R, S, H) = W_parts [p gamma(u)] + b (without the zeta block), colour (1, R, S, H/2) =
        W_pose [p gamma(xi)] + W_dirs [p gamma(d)] + biases, and the segmentation probabilities (R, S, P).
    """
    head = model.head
    r_count, s_count, p_count, _ = u.shape
    density, weights, probs, sample, part = _in_box_density(model, u, in_box, encoded_zeta)

    def per_sample(values: torch.Tensor) -> torch.Tensor:  # (M,) pair values -> (RS, P), zero off the pairs
        return torch.zeros(r_count * s_count, p_count, dtype=u.dtype, device=u.device).index_put((sample, part), values)

    table = _colour_table(model, pose, d_local).to(u.dtype)  # (R, P, H/2)
    # the colour sums sum_i p_i table[r, i] of a ray's samples are one (S, P) x (P, H/2) product per ray
    per_part = per_sample(weights)
    colour_bias = (head.color_embed["pose"].bias[0] + head.color_embed["dirs"].bias[0]).to(u.dtype)
    colour = torch.baddbmm(colour_bias, per_part.reshape(r_count, s_count, p_count), table)
    segmentation = per_sample(probs)
    return (
        density.reshape(1, r_count, s_count, -1),
        colour.reshape(1, r_count, s_count, -1),
        segmentation.reshape(r_count, s_count, p_count),
    )


def _in_box_density(model, u: torch.Tensor, in_box: torch.Tensor, encoded_zeta: torch.Tensor):
    """The part-block sum of the density input over in-box pairs, and the pairs' weights.

    Returns:
        density (R*S, H) = W_parts [p gamma(u)] + b; per in-box pair (M,): the block weights p (rescaled for NARF_D),
        the segmentation probabilities, the flat sample index and the part index.
    """
    head = model.head
    r_count, s_count, p_count, _ = u.shape
    n_samples = r_count * s_count
    ray, in_ray, part = in_box_pairs(in_box)
    sample = ray * s_count + in_ray
    # u needs a gradient when the poses are refined (docs/model.md §6): gathered with index_select, as below
    u_pairs = u.reshape(-1, 3).index_select(0, sample * p_count + part)
    grids, selector = getattr(model, "grids", None), getattr(model, "selector", None)
    # gamma_10(u) (M, 60) feeds the selector, and the density unless the parts' grids do (M, L F)
    encoded = model.encode_points(u_pairs) if grids is None or selector is not None else None
    block_input = encoded if grids is None else model.grid_points(u_pairs, part)
    block_width = block_input.shape[-1]
    counts = torch.bincount(part, minlength=p_count).tolist()
    compute = matmul_dtype(block_input)  # each operand cast once for every part (see matmul_dtype)
    w_density = head.density_embed["parts"].effective_weight()
    # an empty chunk gives an empty block (every sample may miss every box)
    # one split (one backward node) rather than a slice per part, whose backwards each fill a full-size gradient
    if compute == w_density.dtype:
        blocks = w_density[0].split(block_width, dim=-1)  # P x (H, 60 or L F): the column block of each part
    else:  # one cast, to the contiguous blocks that autocast's per-part casts would give
        blocks = w_density[0].to(compute).unflatten(-1, (-1, block_width)).transpose(0, 1).contiguous().unbind(0)
    chunks = torch.split(block_input.to(compute), counts)
    features = torch.cat([chunk @ block.T for chunk, block in zip(chunks, blocks)])
    if selector is not None:
        # a cast of its own: the two uses' gradients are summed in encoded's dtype, as under autocast's own casts
        logit = selector_logits(selector, torch.split(encoded.to(compute), counts), ray, part, encoded_zeta)
        if model.selector_kind == "softmax":
            probs = segment_softmax(logit, sample, n_samples)
        else:
            probs = torch.sigmoid(logit)
        norm = torch.zeros(n_samples, dtype=u.dtype, device=u.device).index_add(0, sample, probs**2).sqrt()
        weights = probs * math.sqrt(p_count) / norm.index_select(0, sample).clamp_min(1e-12)
    else:
        n_in = torch.zeros(n_samples, dtype=u.dtype, device=u.device).index_add(
            0, sample, torch.ones_like(sample, dtype=u.dtype)
        )
        weights, probs = torch.ones_like(sample, dtype=u.dtype), 1.0 / n_in[sample]
    # the biases, broadcast to every sample, are the tensors the sums are added into (one pass over (RS, H))
    density = head.density_embed["parts"].bias[0].to(u.dtype).expand(n_samples, -1)
    return density.index_add(0, sample, weights[:, None] * features), weights, probs, sample, part


def _colour_table(model, pose, d_local: torch.Tensor) -> torch.Tensor:
    """Per ray and part: W_pose,i gamma(xi_i/pi) + W_dirs,i gamma(d_i), (R, P, H/2)."""
    encoded_xi = model.encode_pose(pose.pose_features)  # (R, P, 48)
    encoded_d = model.encode_dirs(d_local)  # (R, P, 24)
    p_count, head = encoded_xi.shape[1], model.head
    w_pose = head.color_embed["pose"].effective_weight()[0].reshape(-1, p_count, 48)  # (H/2, P, 48)
    w_dirs = head.color_embed["dirs"].effective_weight()[0].reshape(-1, p_count, 24)
    return torch.einsum("hpk,rpk->rph", w_pose, encoded_xi) + torch.einsum("hpk,rpk->rph", w_dirs, encoded_d)
