"""``lerobot-idr-policy-server [--host=127.0.0.1] [--port=8080] ...``: lerobot's async inference
policy server, able to serve ``idr`` policies.

lerobot's server does not load plugins and checks the policy type a robot client sends against
a fixed list (``lerobot.async_inference.constants.SUPPORTED_POLICIES``). This launcher imports
the plugin (registering ``idr``), adds ``idr`` to that list, then runs lerobot's own ``serve``
with the same arguments. The robot client is lerobot's, unchanged:
``--policy_type=idr --pretrained_name_or_path=<IDR folder>``.

Security: lerobot's async payloads are pickled, so whoever reaches the port can run code on
this machine. The server binds to loopback unless ``--host`` says otherwise, and this launcher
warns when it does.
"""

from __future__ import annotations

import ipaddress
import logging
import sys

LOOPBACK_NAMES = ("localhost",)


def allow_idr() -> None:
    """Register the plugin and let lerobot's server accept policy type ``idr``."""
    from lerobot.async_inference import constants

    import lerobot_policy_idr  # noqa: F401  (registers the idr policy type)

    if "idr" not in constants.SUPPORTED_POLICIES:
        constants.SUPPORTED_POLICIES.append("idr")  # the list policy_server imported


def is_loopback(host: str) -> bool:
    if host in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def host_of(argv: list[str]) -> str:
    for i, arg in enumerate(argv):
        if arg.startswith("--host="):
            return arg.split("=", 1)[1]
        if arg == "--host" and i + 1 < len(argv):
            return argv[i + 1]
    return "localhost"  # lerobot's PolicyServerConfig default


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    host = host_of(argv)
    if not is_loopback(host):
        logging.warning(
            "lerobot-idr-policy-server: listening on %s, not loopback: the async protocol "
            "unpickles what clients send, so anyone who can reach this port can run code "
            "here. Bind to 127.0.0.1 and tunnel (ssh -L), or firewall the port.",
            host,
        )
    allow_idr()
    from lerobot.async_inference.policy_server import serve

    sys.argv = [sys.argv[0], *argv]
    serve()


if __name__ == "__main__":
    main()
