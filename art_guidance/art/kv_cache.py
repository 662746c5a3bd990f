"""Key/value-cached incremental decoding of `ArtModel` for autoregressive rollouts.

A rollout step i feeds only the tokens that are new since the previous step, the control
u(t_{i-1}) just planned and the goal, R, C and state tokens of step i (five tokens, four at the
first step), and reads the control prediction from the state token. The keys and values of all
earlier tokens stay in preallocated per-layer buffers, so a step costs one step's tokens, not
the whole context. A model with one packed token a step (`ArtConfig.tokens_per_step` = 1) feeds
one token a step, all slots filled.

At batch 1 a step is dominated by per-call overhead (a hundred tiny kernels), so the step is a
lean function over raw weight tensors packed once from the model: the five modality embeddings
become one (17 -> d) product over slot-packed features, the modality biases and the time-step
embedding one (5 K, d) table; activations stay 2-D (B n, d) so every projection is one `addmm`
on a pre-transposed weight with the residual added in the same call; queries, keys and values
come from one fused product; attention is one `scaled_dot_product_attention` call for all heads
with an additive causal mask; the last layer computes its attention and MLP for the state token
only. Call it under `torch.inference_mode()`. It is tested against the module's full-context
forward pass (`rollout(..., use_cache=False)`).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from art_guidance.art.config import FEATURES, MODALITIES, SLOTS, check_steps
from art_guidance.art.model import ArtModel

_LAYER_NAMES = ("ln1.weight", "ln1.bias", "qkv.weight", "qkv.bias", "proj.weight", "proj.bias",
                "ln2.weight", "ln2.bias", "fc.weight", "fc.bias", "out.weight", "out.bias")
_TRANSPOSED = {"qkv.weight", "proj.weight", "fc.weight", "out.weight"}


class CachedDecoder:
    """Incremental, KV-cached evaluation of a trained `ArtModel` (inference only).

    Attributes:
        dtype, device: of the packed weights (those of the model).
    """

    def __init__(self, model: ArtModel) -> None:
        """Pack the weights of `model` (a snapshot: later training does not affect it)."""
        cfg = self._cfg = model.cfg
        with torch.no_grad():
            w = {k: v.detach().clone() for k, v in model.state_dict().items()}
        d = cfg.width
        self.dtype, self.device = w["ln_f.weight"].dtype, w["ln_f.weight"].device
        embed = torch.zeros(FEATURES, d, dtype=self.dtype, device=self.device)  # (17, d)
        for m in MODALITIES:
            embed[SLOTS[m]] = w[f"embed.{m}.weight"].t()
        self._embed_t = embed
        tok_bias = torch.stack([w[f"embed.{m}.bias"] for m in MODALITIES])  # (5, d)
        tps = self._tps = cfg.tokens_per_step
        if tps == 1:  # a packed token sums the five embeddings
            tok_bias = tok_bias.sum(0, keepdim=True)  # (1, d)
        table = w["time_embed.weight"][:, None, :] + tok_bias[None]  # (K, tps, d)
        self._bias_table = table.reshape(cfg.context * tps, d)  # (tps K, d)
        self._ln_e = (w["embed_ln.weight"], w["embed_ln.bias"])
        self._ln_f = (w["ln_f.weight"], w["ln_f.bias"])
        self._head_t = (w["head_control.bias"], w["head_control.weight"].t().contiguous())
        self._layers = [tuple(w[f"blocks.{i}.{n}"].t().contiguous() if n in _TRANSPOSED
                              else w[f"blocks.{i}.{n}"] for n in _LAYER_NAMES)
                        for i in range(cfg.n_layers)]
        self._relu = cfg.activation == "relu"
        self._eps = model.ln_f.eps
        self._shape = (d,)
        n_tok = cfg.context * tps
        causal = torch.ones(n_tok, n_tok, dtype=torch.bool, device=self.device).tril()
        self._mask = torch.zeros(n_tok, n_tok, dtype=self.dtype, device=self.device)
        self._mask.masked_fill_(~causal, float("-inf"))  # additive: faster than bool on CPU
        self._kv: list[torch.Tensor] = []
        self._bias = self._bias_table
        self.np_dtype = torch.empty(0, dtype=self.dtype).numpy().dtype

    def reset(self, batch: int, n_steps: int, t0: int) -> None:
        """Start a new batch of rollouts of `n_steps` steps whose first time index is `t0`.

        Raises:
            ValueError: if the steps do not fit the context (t0 + n_steps > K).
        """
        cfg = self._cfg
        check_steps(cfg, n_steps, t0)
        n_tok = n_steps * self._tps
        shape = (2, batch, cfg.n_heads, n_tok, cfg.head_dim)
        if not self._kv or self._kv[0].shape[1] != batch or self._kv[0].shape[3] < n_tok:
            self._kv = [torch.empty(shape, dtype=self.dtype, device=self.device)
                        for _ in range(cfg.n_layers)]  # each (2, B, H, tps T, hd)
        self._bias = self._bias_table[self._tps * t0:]  # (tps (K - t0), d)

    def step(self, feats: torch.Tensor, p0: int) -> torch.Tensor:
        """Feed the tokens at positions p0 .. p0 + n - 1 and predict the control of the last.

        Args:
            feats: (B, n, 17) slot-packed normalised token features (see config.SLOTS); the
                last token must be a state token (with one token a step: every slot filled,
                the control slot holding the previous step's control).
            p0: position of the first new token in the rollout's token sequence; every earlier
                position must have been fed before (the cache holds them).

        Returns:
            (B, 3) normalised control predicted from the last token.
        """
        b, n, _ = feats.shape
        p1 = p0 + n
        h = torch.mm(feats.reshape(b * n, FEATURES), self._embed_t)  # (B n, d)
        h = h.view(b, n, -1).add_(self._bias.narrow(0, p0, n)).view(b * n, -1)  # (B n, d)
        h = torch.layer_norm(h, self._shape, *self._ln_e, self._eps)  # (B n, d)
        mask = self._mask.narrow(0, p0, n).narrow(1, 0, p1)  # (n, p1) additive causal mask
        last = len(self._layers) - 1
        for i, layer in enumerate(self._layers):
            h = self._block(h, layer, self._kv[i], b, n, p0, mask if i < last else None)
        h = torch.layer_norm(h, self._shape, *self._ln_f, self._eps)  # (B, d)
        return torch.addmm(*self._head_t[:1], h, self._head_t[1])  # (B, 3)

    def step_numpy(self, feats, p0: int):
        """`step` on a numpy view (B, n, 17) of `np_dtype` (shared, not copied); returns the
        (B, 3) or (B, 4) control as numpy (the interface `onnx_art.OnnxDecoder` shares)."""
        x = torch.from_numpy(feats)
        with torch.inference_mode():
            if self.device.type != "cpu":
                x = x.to(self.device)
            return self.step(x, p0).cpu().numpy()

    def _block(self, h: torch.Tensor, layer: tuple, kv: torch.Tensor, b: int, n: int, p0: int,
               mask: torch.Tensor | None) -> torch.Tensor:
        """One block on h (B n, d); with `mask` None only the last token's row is returned."""
        ln1_w, ln1_b, qkv_wt, qkv_b, proj_wt, proj_b, ln2_w, ln2_b, fc_wt, fc_b, out_wt, out_b = \
            layer
        heads = self._cfg.n_heads
        x = torch.layer_norm(h, self._shape, ln1_w, ln1_b, self._eps)  # (B n, d)
        qkv = torch.addmm(qkv_b, x, qkv_wt).view(b, n, 3, heads, -1).permute(2, 0, 3, 1, 4)
        kv.narrow(3, p0, n).copy_(qkv.narrow(0, 1, 2))  # cache K, V: (2, B, H, n, hd)
        k, v = kv.narrow(3, 0, p0 + n).unbind(0)  # each (B, H, p1, hd)
        q = qkv.select(0, 0)  # (B, H, n, hd)
        if mask is None:  # last layer: the state token's output is the only one read
            h, q, n = h.view(b, n, -1).select(1, n - 1), q.narrow(2, n - 1, 1), 1  # (B, d)
        a = F.scaled_dot_product_attention(q, k, v, attn_mask=mask)  # (B, H, n, hd)
        a = a.transpose(1, 2).reshape(b * n, -1)  # (B n, d)
        h = torch.addmm(h, a, proj_wt).add_(proj_b)  # (B n, d) residual
        x = torch.layer_norm(h, self._shape, ln2_w, ln2_b, self._eps)  # (B n, d)
        f = torch.addmm(fc_b, x, fc_wt)  # (B n, 4d)
        f = f.relu_() if self._relu else F.gelu(f)
        return torch.addmm(h, f, out_wt).add_(out_b)  # (B n, d) residual
