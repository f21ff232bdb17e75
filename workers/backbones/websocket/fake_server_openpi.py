"""The fake server's closed-form policy (``workers.backbones.websocket.fake_server``) served by
the real ``openpi-server`` package (``WebsocketPolicyServer`` around an ``openpi_client``
BasePolicy), in its own interpreter (``.venv-openpi``: openpi-client pins numpy < 2).
Run as ``.venv-openpi/bin/python -m workers.backbones.websocket.fake_server_openpi --port P
[--batch] ...``; ``--codec-check`` instead round-trips a message through
openpi_client.msgpack_numpy (stdin to stdout) for the codec test."""

from __future__ import annotations

import sys

from openpi_client import base_policy, msgpack_numpy

from workers.backbones.websocket.fake_server import metadata_of, parser, respond


class ClosedFormPolicy(base_policy.BasePolicy):
    def __init__(self, gains: tuple[float, float, float, int, int]) -> None:
        self.gains = gains

    def infer(self, obs: dict) -> dict:
        return {"actions": respond(obs, self.gains)}


def main() -> None:
    if sys.argv[1:] == ["--codec-check"]:  # theirs unpacks ours, and packs it back
        sys.stdout.buffer.write(msgpack_numpy.packb(msgpack_numpy.unpackb(sys.stdin.buffer.read())))
        return
    from openpi_server.websocket_policy_server import WebsocketPolicyServer

    args = parser().parse_args()
    gains = (args.img_gain, args.state_gain, args.noise_std, args.horizon, args.action_dim)
    server = WebsocketPolicyServer(
        ClosedFormPolicy(gains), host="127.0.0.1", port=args.port, metadata=metadata_of(args)
    )
    print("ready", flush=True)
    server.serve_forever()


if __name__ == "__main__":
    main()
