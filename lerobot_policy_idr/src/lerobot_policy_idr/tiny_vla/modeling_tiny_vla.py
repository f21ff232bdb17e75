"""The tiny VLA model (a lerobot ``PreTrainedPolicy``); see configuration_tiny_vla."""

from __future__ import annotations

import re
from collections import deque

import torch
import torch.nn.functional as F
from idr_core.features import ACTION, OBS_STATE
from lerobot.policies.pretrained import PreTrainedPolicy
from torch import Tensor, nn

from lerobot_policy_idr.tiny_vla.configuration_tiny_vla import TinyVLAConfig


def tokenize(texts: list[str], vocab: list[str], max_tokens: int) -> Tensor:
    """Lower-cased words -> ids (0 pad, 1 unknown, 2 + index in vocab), (B, max_tokens)."""
    index = {w: i + 2 for i, w in enumerate(vocab)}
    out = torch.zeros(len(texts), max_tokens, dtype=torch.long)
    for b, text in enumerate(texts):
        ids = [index.get(w, 1) for w in re.findall(r"[a-z]+", text.lower())][:max_tokens]
        out[b, : len(ids)] = torch.tensor(ids, dtype=torch.long)
    return out


class SpatialSoftmax(nn.Module):
    """(B, C, H, W) -> (B, 2C) expected (x, y) of each channel's softmax over the image."""

    def forward(self, x: Tensor) -> Tensor:
        b, c, h, w = x.shape
        attn = F.softmax(x.flatten(2), dim=-1).view(b, c, h, w)
        ys = torch.linspace(-1, 1, h, device=x.device, dtype=x.dtype)
        xs = torch.linspace(-1, 1, w, device=x.device, dtype=x.dtype)
        return torch.cat([(attn.sum(2) * xs).sum(-1), (attn.sum(3) * ys).sum(-1)], dim=1)


class CameraEncoder(nn.Module):
    """A small CNN whose last layer is FiLM-modulated by the instruction."""

    def __init__(
        self, channels: tuple[int, ...], text_dim: int, strides: tuple[int, ...] | None = None
    ) -> None:
        super().__init__()
        strides = strides or (2,) * len(channels)
        layers, c_in = [], 5  # RGB + two coordinate channels (CoordConv): positions are the task
        for i, (c, s) in enumerate(zip(channels, strides, strict=True)):
            layers.append(
                nn.Conv2d(c_in, c, 5 if i == 0 else 3, stride=s, padding=2 if i == 0 else 1)
            )
            c_in = c
        self.convs = nn.ModuleList(layers)
        self.film = nn.Linear(text_dim, 2 * channels[-1])
        self.keypoints = SpatialSoftmax()
        self.out_dim = 2 * channels[-1]

    def forward(self, img: Tensor, text: Tensor) -> Tensor:
        b, _, h, w = img.shape
        ys = (
            torch.linspace(-1, 1, h, device=img.device, dtype=img.dtype)
            .view(1, 1, h, 1)
            .expand(b, 1, h, w)
        )
        xs = (
            torch.linspace(-1, 1, w, device=img.device, dtype=img.dtype)
            .view(1, 1, 1, w)
            .expand(b, 1, h, w)
        )
        x = torch.cat([img * 2 - 1, xs, ys], dim=1)
        for conv in self.convs[:-1]:
            x = F.relu(conv(x))
        x = self.convs[-1](x)
        gamma, beta = self.film(text).chunk(2, dim=-1)
        x = F.relu(x * (1 + gamma[:, :, None, None]) + beta[:, :, None, None])
        return self.keypoints(x)


class TinyVLAPolicy(PreTrainedPolicy):
    config_class = TinyVLAConfig
    name = "tiny_vla"

    def __init__(self, config: TinyVLAConfig, **kwargs: object) -> None:
        super().__init__(config)
        config.validate_features()
        self.config = config
        self.image_keys = sorted(config.image_features)
        self.state_dim = config.robot_state_feature.shape[0]
        self.action_dim = config.action_feature.shape[0]
        self.word_emb = nn.Embedding(len(config.vocab) + 2, config.text_dim, padding_idx=0)
        self.pos_emb = nn.Parameter(torch.zeros(config.max_tokens, config.text_dim))
        self.text_rnn = nn.GRU(config.text_dim, config.text_dim, batch_first=True)
        self.cameras = nn.ModuleDict(
            {
                k.replace(".", "_"): CameraEncoder(
                    tuple(config.cnn_channels), config.text_dim, tuple(config.cnn_strides)
                )
                for k in self.image_keys
            }
        )
        feat = sum(e.out_dim for e in self.cameras.values()) + self.state_dim + config.text_dim
        self.head = nn.Sequential(
            nn.Linear(feat, config.hidden_dim),
            nn.ReLU(),
            nn.Dropout(config.dropout),
            nn.Linear(config.hidden_dim, config.hidden_dim),
            nn.ReLU(),
            nn.Linear(config.hidden_dim, config.chunk_size * self.action_dim),
        )
        state_mask = torch.ones(self.state_dim)
        state_mask[list(config.ignored_state_dims)] = 0.0
        self.register_buffer("state_mask", state_mask, persistent=False)
        self._queue: deque[Tensor] = deque(maxlen=config.n_action_steps)

    def get_optim_params(self) -> dict:
        return self.parameters()

    def reset(self) -> None:
        self._queue.clear()

    def encode_text(self, texts: list[str], device: torch.device) -> Tensor:
        tokens = tokenize(texts, self.config.vocab, self.config.max_tokens).to(device)
        x = self.word_emb(tokens) + self.pos_emb
        lengths = (tokens > 0).sum(1).clamp(min=1).cpu()
        packed = nn.utils.rnn.pack_padded_sequence(
            x, lengths, batch_first=True, enforce_sorted=False
        )
        _, h = self.text_rnn(packed)
        return h[-1]

    def _predict(self, batch: dict) -> Tensor:
        state = batch[OBS_STATE]
        texts = batch.get("task")
        if texts is None:
            raise ValueError("tiny_vla needs the instruction under batch['task']")
        if isinstance(texts, str):
            texts = [texts] * state.shape[0]
        text = self.encode_text(list(texts), state.device)
        feats = [
            self.cameras[k.replace(".", "_")](self._sized(batch[k]), text) for k in self.image_keys
        ]
        out = self.head(torch.cat([*feats, state * self.state_mask, text], dim=-1))
        return out.view(-1, self.config.chunk_size, self.action_dim)

    def _sized(self, img: Tensor) -> Tensor:
        """The image at ``resize_images_to`` px where it is set and the image differs."""
        n = self.config.resize_images_to
        if n is None or tuple(img.shape[-2:]) == (n, n):
            return img
        return F.interpolate(img, size=(n, n), mode="bilinear", antialias=True, align_corners=False)

    def forward(self, batch: dict) -> tuple[Tensor, dict]:
        pred = self._predict(batch)
        target = batch[ACTION]
        loss = F.mse_loss(pred, target, reduction="none")
        if "action_is_pad" in batch:
            loss = loss * (~batch["action_is_pad"]).unsqueeze(-1)
        loss = loss.mean()
        return loss, {"mse": float(loss.detach())}

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict, **kwargs: object) -> Tensor:
        return self._predict(batch)

    @torch.no_grad()
    def select_action(self, batch: dict, **kwargs: object) -> Tensor:
        if not self._queue:
            chunk = self._predict(batch)[:, : self.config.n_action_steps]
            self._queue.extend(chunk.transpose(0, 1))
        return self._queue.popleft()
