"""A fake policy server speaking openpi's websocket protocol, for the remote backbone's tests
and benchmarks: closed-form, not learned. Named as a fake.

Its policy is closed-form, so IDR's effects have exact expected values: every action of the
(T, D) chunk is ``img_gain * m + state_gain * s + noise_std * noise``, with m the mean of the
``observation/image`` pixels in [0, 1] and s the mean of ``observation/state``; so
E_img = img_gain * m * sqrt(T * D) and E_prop = state_gain * |s| * sqrt(T * D) for zeroing.
Run as ``python -m workers.backbones.websocket.fake_server --port P [--batch] [--noise]
[--fail-on N]``; ``--fail-on N`` answers the N-th request with a traceback string (the
protocol's error form), ``--exit-on N`` dies there (a server that crashes mid-episode)."""

from __future__ import annotations

import argparse
import os
import traceback

import numpy as np

from workers.backbones.websocket import codec


def act(
    obs: dict, img_gain: float, state_gain: float, noise_std: float, T: int, D: int
) -> np.ndarray:
    m = float(np.asarray(obs["observation/image"], dtype=np.float64).mean() / 255.0)
    s = float(np.asarray(obs["observation/state"], dtype=np.float64).mean())
    a = np.full((T, D), img_gain * m + state_gain * s)
    if noise_std and "noise" in obs:
        a = a + noise_std * np.asarray(obs["noise"], dtype=np.float64)
    return a.astype(np.float32)


def respond(obs: dict, gains: tuple[float, float, float, int, int]) -> np.ndarray:
    """The actions for an observation map, or for a batched one (``prompt`` a list)."""
    if isinstance(obs["prompt"], list):
        rows = [{k: v[i] for k, v in obs.items()} for i in range(len(obs["prompt"]))]
        return np.stack([act(r, *gains) for r in rows])
    return act(obs, *gains)


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--batch", action="store_true")
    ap.add_argument("--noise", action="store_true")
    ap.add_argument("--fail-on", type=int, default=-1)
    ap.add_argument("--exit-on", type=int, default=-1)
    ap.add_argument("--img-gain", type=float, default=2.0)
    ap.add_argument("--state-gain", type=float, default=0.5)
    ap.add_argument("--noise-std", type=float, default=0.1)
    ap.add_argument("--horizon", type=int, default=4)
    ap.add_argument("--action-dim", type=int, default=7)
    return ap


def metadata_of(args: argparse.Namespace) -> dict:
    shape = [args.horizon, args.action_dim]
    return {"idr": {"batch": args.batch, "noise": args.noise, "noise_shape": shape}}


def main(argv: list[str] | None = None) -> None:
    from websockets.sync.server import serve

    args = parser().parse_args(argv)
    calls = {"n": 0}
    metadata = metadata_of(args)
    gains = (args.img_gain, args.state_gain, args.noise_std, args.horizon, args.action_dim)

    def handler(ws) -> None:  # type: ignore[no-untyped-def]
        ws.send(codec.packb(metadata))
        for frame in ws:
            calls["n"] += 1
            if calls["n"] == args.exit_on:
                os._exit(9)
            try:
                if calls["n"] == args.fail_on:
                    raise RuntimeError("injected failure in the fake policy")
                ws.send(codec.packb({"actions": respond(codec.unpackb(frame), gains)}))
            except Exception:
                ws.send(traceback.format_exc())
                ws.close(1011, "internal error")
                return

    with serve(handler, "127.0.0.1", args.port, compression=None, max_size=None) as server:
        print("ready", flush=True)
        server.serve_forever()


if __name__ == "__main__":
    main()
