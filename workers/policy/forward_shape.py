"""Forwards of one fixed shape, so that a row's actions do not depend on its batch mates.

A network's output for one row is a pure function of that row only at a fixed batch shape:
the kernels of a matrix product pick their blocking (and so the order of their float sums) by
the batch size, and on a CPU by the number of threads. Measured here (2-core CPU, float32):
between forwards of 3 and 96 rows, the same row's actions move by up to 7.6e-6 (tiny VLA) and
9e-7 (ACT); ACT's also move by 1.2e-6 between 1 and 2 torch threads; at one shape and one thread
count a row's actions are bit-identical whatever its position and its mates
(``tests/workers/policy/test_forward_shape.py``). Mates can also change a row's float order
through their content: the tiny VLA packs its RNN's sequences by instruction length (9.5e-7), so
the service gives each forward one instruction (``service.infer_many(by_instruction=True)``), as
an in-actor forward has. In closed loop a difference in the 8th digit grows into another
trajectory, so a run is reproducible only when every forward has one shape and one instruction.

:class:`FixedShapeBackbone` cuts a batch into forwards of exactly ``rows`` rows (the last one
padded with copies of its last row, whose outputs are dropped). Both executor modes use it with
the same ``rows`` when asked (``executor.forward_rows``), and the shared policy service always
does unless ``executor.batching=dynamic``: see :func:`numerics_label` for the names of the paths.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from idr_core.tensors import is_torch

from workers.backbones.base import Observation, concat_observations


class NumericsError(RuntimeError):
    """A backbone that cannot give reproducible numbers at a fixed forward shape."""


def numerics_label(
    rows: int | Literal["dynamic"] | None,
    threads: int | None,
    batched: bool = True,
    remote: bool = False,
) -> str:
    """The name of a numerical path: two episodes with the same label, config and seed have the
    same actions bit for bit (on the same device and library versions).

    ``rows=R``: every forward has R rows; ``request``: each inference's own rows (1, or 3 for
    IDR: in-actor without forward_rows); ``dynamic``: as many rows as the batch gathered
    (shared, executor.batching=dynamic: not reproducible); ``per_pass``: a backbone that does
    not batch, one row per forward in every mode; ``remote``: the policy server's own.
    """
    if remote:
        return "remote"
    if not batched:
        shape = "per_pass"
    elif rows is None:
        shape = "request"
    else:
        shape = "dynamic" if rows == "dynamic" else f"rows={rows}"
    return shape if threads is None else f"{shape} threads={threads}"


def set_torch_threads(threads: int | None) -> None:
    """torch's intra-op threads (CPU kernels' float order depends on them); None: unchanged."""
    if threads is None:
        return
    import torch

    if torch.get_num_threads() != threads:
        torch.set_num_threads(threads)


def _rows(x: Any, idx: np.ndarray) -> Any:
    if is_torch(x):
        import torch

        return x[torch.as_tensor(idx, device=x.device)]
    return np.asarray(x)[idx]


def take_rows(obs: Observation, idx: np.ndarray) -> Observation:
    """The rows ``idx`` of ``obs`` (a row may repeat), per-row extras included."""
    extras = {k: [v[i] for i in idx] if isinstance(v, list) else v for k, v in obs.extras.items()}
    return Observation(
        images={cam: _rows(img, idx) for cam, img in obs.images.items()},
        state=_rows(obs.state, idx),
        instruction=[obs.instruction[i] for i in idx],
        do_image=None if obs.do_image is None else np.asarray(obs.do_image)[idx],
        do_state=None if obs.do_state is None else np.asarray(obs.do_state)[idx],
        extras=extras,
    )


def cat_rows(xs: list[Any]) -> Any:
    """Arrays (torch or numpy, as given) stacked along the batch dim."""
    if is_torch(xs[0]):
        import torch

        return torch.cat(xs, dim=0)
    return np.concatenate(xs, axis=0)


def padded(n: int, rows: int) -> np.ndarray:
    """Row indices of one forward of ``rows`` rows holding rows 0..n-1 (n <= rows): the last
    row repeated into the padding."""
    return np.minimum(np.arange(rows), n - 1)


@dataclass
class FixedShapeBackbone:
    """``inner`` called only on batches of exactly ``rows`` rows (see the module docstring);
    every other member is the inner backbone's."""

    inner: Any
    rows: int

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def predict_chunk(self, obs: Observation, noise: Any = None, intervention: Any = None) -> Any:
        n = obs.batch_size
        outs = []
        for start in range(0, n, self.rows):
            m = min(self.rows, n - start)
            idx = start + padded(m, self.rows)
            out = self.inner.predict_chunk(
                take_rows(obs, idx),
                noise=None if noise is None else _rows(noise, idx),
                intervention=intervention,
            )
            outs.append(out[:m])
        return outs[0] if len(outs) == 1 else cat_rows(outs)


def fix_forward_shape(policy: Any, rows: int | str | None, threads: int | None) -> str:
    """Give ``policy`` (an IDRWrapper) forwards of ``rows`` rows where that means anything (a
    local backbone that batches its passes); the label of the numerical path it then follows."""
    remote = bool(getattr(policy.backbone, "remote", False))
    if isinstance(rows, int) and policy.batched and not remote:
        policy.backbone = FixedShapeBackbone(policy.backbone, rows)
    return numerics_label(rows, threads, policy.batched, remote)  # type: ignore[arg-type]


def check_row_independence(backbone: Any, obs: Observation, noise: Any, rows: int) -> None:
    """Raise NumericsError unless ``obs``'s rows come out of a forward of ``rows`` rows the same
    at the front, padded with copies, and at the back, after other rows (its rows with images
    inverted and state negated). Costs two forwards; run once, on the first request a worker gets."""
    n = obs.batch_size
    if n > rows // 2:  # no room for other rows before it: nothing to compare
        return
    front = backbone.predict_chunk(take_rows(obs, padded(n, rows)), noise=_pad(noise, n, rows))
    others = take_rows(obs, (np.arange(rows - n) % n)[::-1].copy())
    others.images = {cam: 1.0 - img for cam, img in others.images.items()}
    others.state = -others.state
    batch = concat_observations([others, obs])
    back_noise = None if noise is None else cat_rows([_rows(noise, np.arange(rows - n) % n), noise])
    back = backbone.predict_chunk(batch, noise=back_noise)
    a, b = as_numpy(front[:n]), as_numpy(back[rows - n :])
    if not np.array_equal(a, b):
        diff = float(np.abs(a - b).max())
        raise NumericsError(
            f"backbone {getattr(backbone, 'name', type(backbone).__name__)!r}: a row's actions "
            f"change with its position and batch mates in a forward of {rows} rows (by up to "
            f"{diff:.3g}), so no forward shape makes its runs reproducible. Use "
            "executor.batching=dynamic (runs then differ in float rounding, said in the run's "
            "protocol record) or executor.policy=in_actor"
        )


def _pad(noise: Any, n: int, rows: int) -> Any:
    return None if noise is None else _rows(noise, padded(n, rows))


def as_numpy(x: Any) -> np.ndarray:
    """A torch tensor (float32 on the CPU) or an array, as numpy."""
    return x.detach().float().cpu().numpy() if hasattr(x, "detach") else np.asarray(x)
