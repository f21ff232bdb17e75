"""The MLflow tracking store: its URI, whether it answers, its lock and its schema, checked before
a run starts (bad input is refused before any work)."""

from __future__ import annotations

import os
import sqlite3
from pathlib import Path
from typing import Any

from pipeline.errors import ConfigError

HTTP_RETRY_DEFAULTS = {  # for a tracking server (the user's own settings win)
    "MLFLOW_HTTP_REQUEST_MAX_RETRIES": "2",
    "MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR": "1",
    "MLFLOW_HTTP_REQUEST_TIMEOUT": "30",
}


def default_uri(run_dir: Path) -> str:
    return f"sqlite:///{(run_dir.resolve().parent / 'mlflow.db')}"


def resolve_uri(uri: str | None, run_dir: Path) -> str:
    return uri or default_uri(run_dir)


def probe(uri: str, timeout: float = 5.0) -> None:
    """Fail within seconds when a tracking server does not answer (MLflow itself retries for minutes)."""
    if not uri.startswith(("http://", "https://")):
        return
    import urllib.error
    import urllib.request

    try:
        with urllib.request.urlopen(uri.rstrip("/") + "/health", timeout=timeout) as r:
            r.read()
    except (urllib.error.URLError, OSError) as e:
        raise RuntimeError(
            f"MLflow store {uri} is not usable: tracking server does not answer ({e})"
        ) from None


def sqlite_path(uri: str) -> Path | None:
    return Path(uri.removeprefix("sqlite:///")) if uri.startswith("sqlite:///") else None


def store_lock(path: Path) -> Any:
    """The lock under which a SQLite store is created, migrated and checked: MLflow creates a
    new store's schema on first use, and two drivers doing it at once collide (``duplicate
    column name``); held for seconds, once per driver."""
    from filelock import FileLock

    return FileLock(str(path) + ".lock", timeout=300)


def check_uri(uri: str) -> None:
    """Refuse, before anything of a run is created, a tracking URI that cannot work: an unknown
    scheme, a SQLite store that is a directory, unwritable, damaged, not an MLflow store or of
    another MLflow version, a tracking server that does not answer. Raises RuntimeError."""
    scheme = uri.split(":", 1)[0].split("+", 1)[0].lower() if ":" in uri else ""
    if scheme not in SCHEMES:
        raise RuntimeError(
            f"{uri!r} has an unknown scheme {scheme or '(none)'!r}: use sqlite:///PATH, "
            "http(s)://HOST:PORT (a tracking server) or postgresql://..."
        )
    path = sqlite_path(uri)
    if path is None:
        probe(uri)
        return
    if path.is_dir():
        raise RuntimeError(f"the SQLite store {path} is a directory: give a file path")
    folder = next(p for p in (path.parent, *path.parent.parents) if p.exists())
    if not os.access(folder, os.W_OK | os.X_OK):
        raise RuntimeError(f"the SQLite store {path} cannot be written ({folder} is not writable)")
    if path.exists() and not os.access(path, os.R_OK | os.W_OK):
        raise RuntimeError(f"the SQLite store {path} is not readable and writable")
    if not path.exists():
        return

    with store_lock(path):  # a store another driver is creating right now is whole after it
        try:
            check_store(uri, damaged_hint=True)
        except ConfigError as e:
            raise RuntimeError(str(e)) from None


def bounded_client(uri: str) -> Any:
    """An MlflowClient whose HTTP requests give up within about a minute (30 s timeout, 2
    retries) instead of MLflow's defaults (7 tries with doubling backoff: minutes against a
    server that is gone, slow or unresolvable); the user's own MLFLOW_HTTP_* settings win.
    Every MLflow client the CLI makes comes from here."""
    from mlflow import MlflowClient

    if uri.startswith(("http://", "https://")):
        for key, value in HTTP_RETRY_DEFAULTS.items():
            os.environ.setdefault(key, value)
    return MlflowClient(tracking_uri=uri)


def answers(uri: str) -> bool:
    """Whether the store answers: a tracking server its health check, a SQLite store a read
    of its schema version (a damaged or vanished file does not)."""
    path = sqlite_path(uri)
    if path is not None:
        import sqlite3

        if not path.is_file():
            return False
        try:
            with sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=5) as db:
                db.execute("SELECT version_num FROM alembic_version").fetchone()
        except sqlite3.Error:
            return False
        return True
    try:
        probe(uri, timeout=2.0)
    except RuntimeError:
        return False
    return True


def check_store(uri: str, damaged_hint: bool = False) -> None:
    """Refuse, before a UI or a run starts, a SQLite store that is not there, is damaged, is
    not an MLflow store, or that another version of MLflow wrote (its UI would fail on it, or
    offer to migrate it). ``damaged_hint``: the refusal says how a run can go on without it."""
    if not uri.startswith("sqlite:///"):
        return
    path = Path(uri.removeprefix("sqlite:///"))
    if not path.is_file():
        raise ConfigError(
            f"the MLflow store {path} does not exist: run a config with tracking enabled first "
            "(its runs go to <output_root>/mlflow.db), or name a run dir that was tracked"
        )
    aside = (
        f"; move it aside (mv {path} {path}.bad) to start a new store, or set "
        "tracking.enabled=false to run without MLflow"
        if damaged_hint
        else ""
    )
    try:
        with sqlite3.connect(f"file:{path}?mode=ro", uri=True) as db:
            ok = db.execute("PRAGMA quick_check(1)").fetchone()
            if ok is None or ok[0] != "ok":
                raise sqlite3.DatabaseError(f"quick_check: {ok[0] if ok else 'no answer'}")
            row = db.execute("SELECT version_num FROM alembic_version").fetchone()
    except sqlite3.DatabaseError as e:
        raise ConfigError(f"{path} is not a readable MLflow store ({e}){aside}") from None
    found = row[0] if row else None
    known, head = _schema_revisions()
    if found == head:
        return
    import mlflow

    if found in known:
        raise ConfigError(
            f"{path} was written by an older MLflow (schema {found}; this MLflow "
            f"{mlflow.__version__} expects {head}): back it up, then upgrade it with "
            f"`mlflow db upgrade {uri}`, or open it with the MLflow version that wrote it"
        )
    raise ConfigError(
        f"{path} was written by a newer MLflow than this one ({mlflow.__version__}; unknown "
        f"schema {found}): open it with that MLflow's UI (`mlflow ui --backend-store-uri {uri}`)"
    )


def _schema_revisions() -> tuple[set[str], str]:
    """The store schema revisions this MLflow knows, and its head (alembic's script dir)."""
    import mlflow
    from alembic.script import ScriptDirectory

    scripts = ScriptDirectory(str(Path(mlflow.__file__).parent / "store" / "db_migrations"))
    return {s.revision for s in scripts.walk_revisions()}, str(scripts.get_current_head())


#: URI schemes a run can track to: a SQLite file, a tracking server, or a database server
#: (``mlflow server``'s backends; psycopg for PostgreSQL is the ``server`` extra).
SCHEMES = ("sqlite", "http", "https", "postgresql", "mysql", "mssql")
