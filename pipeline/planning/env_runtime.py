"""Pre-flight of where the simulator runs: in the actors' Python, or in an env server.

Before any actor starts, the driver checks what the env needs in the interpreter it will run
in (the env class's ``check_runtime``: simulator packages, a checkout the user points at).
With ``env.python`` it resolves the interpreter, starts a server from it once, checks the
protocol version and runs the check there; a missing interpreter, a server that does not
start or speaks another protocol version, and a missing package or checkout are each one
ConfigError naming the field and the fix.
"""

from __future__ import annotations

import os
from pathlib import Path

from pipeline.planning.config import ConfigError, RunConfig
from workers.envs.base import suite_hooks, suite_info
from workers.envs.factory import env_class, env_entry
from workers.envs.server.client import EnvServerError, ServerSpec, probe_server


def server_spec(cfg: RunConfig) -> ServerSpec | None:
    """The env server the actors start (its interpreter as an absolute path), or None."""
    if cfg.env.python is None:
        return None
    path = Path(cfg.env.python).expanduser()
    hint = suite_info(env_class(cfg.env.suite)).server_setup_hint
    fix = f" ({hint})" if hint else ""
    if not path.exists():
        raise ConfigError(f"env.python={cfg.env.python}: no such interpreter{fix}")
    if not (path.is_file() and os.access(path, os.X_OK)):
        raise ConfigError(f"env.python={cfg.env.python}: not an executable file{fix}")
    # absolute, but a venv's python symlink is kept: resolving it would lose the venv
    return ServerSpec(python=str(path.absolute()), timeout_s=cfg.env.server_timeout_s)


def check_env_runtime(cfg: RunConfig) -> tuple[ServerSpec | None, dict[str, object] | None]:
    """Run the env's runtime check where it will run; the server spec and the server's hello
    (its Python version, for the run's record), or (None, None) in-process."""
    spec = server_spec(cfg)
    if spec is None:
        check = suite_hooks(env_class(cfg.env.suite)).check_runtime
        if check is not None:
            try:
                check(**cfg.env.params)
            except ValueError as e:
                raise ConfigError(str(e)) from None
        return None, None
    try:
        hello = probe_server(spec, env_entry(cfg.env.suite), dict(cfg.env.params))
    except EnvServerError as e:
        raise ConfigError(str(e)) from None
    except ValueError as e:  # the env's own check_runtime, in the server
        raise ConfigError(str(e).split("\n(raised in the env server")[0]) from None
    return spec, hello
