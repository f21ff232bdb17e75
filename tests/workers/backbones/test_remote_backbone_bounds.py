"""The websocket backbone takes no frame longer than ``max_reply_bytes`` from whatever answers at
its host and port: an oversized reply ends the call with RemoteBackboneError naming the bound
(the websockets library refuses the frame on its header), and the next call connects anew. A loopback server of the test's own."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from websockets.sync.server import serve

from workers.backbones.websocket import codec
from workers.backbones.websocket.client import RemoteBackboneError, WebsocketBackbone
from workers.envs.fakes import FakeMarkerEnv
from workers.episode.observation import to_policy_observation


@pytest.fixture
def oversized_server():
    """Sends small metadata on connect, then answers every request with ``reply_bytes`` of
    actions."""
    state = {"reply_bytes": 0}

    def handler(ws) -> None:
        ws.send(codec.packb({"action_horizon": 4, "action_dim": 2}))
        for _ in ws:
            n = state["reply_bytes"] // 4
            ws.send(codec.packb({"actions": np.zeros((n // 2, 2), np.float32)}))

    with serve(handler, "127.0.0.1", 0, max_size=None, compression=None) as server:
        t = threading.Thread(target=server.serve_forever, daemon=True)
        t.start()
        yield server.socket.getsockname()[1], state
        server.shutdown()


def _obs():
    o = FakeMarkerEnv().reset("reach", 0, 0)
    return to_policy_observation(o, o.status.instruction)


def test_a_reply_over_the_bound_is_an_error_and_one_within_it_an_answer(oversized_server):
    port, state = oversized_server
    key_map = {"image:agentview": "image", "state": "state", "prompt": "prompt"}
    backbone = WebsocketBackbone(port=port, key_map=key_map, max_reply_bytes=1 << 20)
    state["reply_bytes"] = 64 << 10
    assert backbone.predict_chunk(_obs()).shape[-1] == 2
    state["reply_bytes"] = 8 << 20  # eight times the bound
    with pytest.raises(RemoteBackboneError, match=r"too big.*max_reply_bytes=1048576"):
        backbone.predict_chunk(_obs())
    state["reply_bytes"] = 64 << 10  # the next call connects anew
    assert backbone.predict_chunk(_obs()).shape[-1] == 2
    backbone.close()
