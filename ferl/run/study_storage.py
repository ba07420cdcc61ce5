"""Where a study lives, and whether the file there may be used (docs/sweeps.md, "The study database").

``hydra.sweeper.storage`` chooses the storage:

* ``sqlite`` (the default): ``<sweep dir>/study.db``, Optuna's RDB storage on SQLite: one machine,
  any number of worker processes on it;
* ``journal``: ``<sweep dir>/study.journal``, Optuna's JournalStorage on a JournalFileBackend: an
  append-only file whose writers take a symlink lock, which NFS honours, so that the tasks of a SLURM
  array on several nodes can share one study (SQLite's own locking is not reliable on NFS);
* a database URL (``sqlite:///path.db``, ``postgresql://…``): Optuna's RDB storage there.

A file that is there already is read before Optuna opens it, read-only, because Optuna's RDB storage
creates its tables in any SQLite file it is given: a file that is not a study database, or that is
corrupt, or that holds other studies than this one, is refused in one line that names it and what it
holds, and is left byte for byte as it was. The study itself is continued only when it is the same
search (``ferl.run.study_space.SearchSpace.identity``).

Beside the file, two small things coordinate the processes that share a study: ``.<file>.claims``,
whose exclusive flock is held while a process looks at the trials and claims the next ones; and
``.<file>.workers/``, one file per live worker process, flocked for the process's life. The kernel
(NFS's lock manager across nodes) drops a flock when its process ends however it ends, so a RUNNING
trial whose worker's flock is free was left by a dead process (``ferl.run.lock`` uses the same idea).
"""

import fcntl
import json
import os
import secrets
import socket
import sqlite3
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import optuna
from optuna.storages import BaseStorage, JournalStorage, RDBStorage
from optuna.storages.journal import JournalFileBackend
from optuna.study import StudyDirection

from ferl.config.params import ConfigError
from ferl.run.lock import flock_taken
from ferl.run.study_space import described

FILES = {"sqlite": "study.db", "journal": "study.journal"}
IDENTITY = "ferl_search"  # the study's user attribute that holds its SearchSpace.identity()
SQLITE_HEADER = b"SQLite format 3\x00"


class StudyError(ConfigError):
    """A study that cannot be used as asked; str(e) is the one line shown to the user."""


@dataclass(frozen=True)
class Location:
    """A study's storage: ``kind`` sqlite, journal or url; ``file`` for the first two; ``url``
    for Optuna's RDB storage; ``home``/``stem``: where and under which name the coordination files lie."""

    kind: str
    file: Path | None
    url: str
    home: Path
    stem: str

    def shown(self) -> str:
        """The file as the user named it, or the URL without its password."""
        if self.file is not None:
            return str(self.file)
        from sqlalchemy.engine import make_url

        return make_url(self.url).render_as_string(hide_password=True)

    @property
    def claims_file(self) -> Path:
        return self.home / f".{self.stem}.claims"

    @property
    def workers_dir(self) -> Path:
        return self.home / f".{self.stem}.workers"


def location(storage: str | None, sweep_dir: Path) -> Location:
    """``hydra.sweeper.storage`` (the module docstring's choices) for a sweep in ``sweep_dir``."""
    choice = str(storage or "sqlite")
    if choice in FILES:
        file = sweep_dir / FILES[choice]
    elif choice.startswith("sqlite:///"):
        file = Path(choice[len("sqlite:///") :])
    elif "://" in choice:
        return Location("url", None, choice, sweep_dir, "study")
    else:
        raise StudyError(
            f"hydra.sweeper.storage={choice} is not allowed: sqlite, journal or a database URL (sqlite:///file.db)"
        )
    kind = "journal" if choice == "journal" else "sqlite"
    return Location(kind, file, f"sqlite:///{file.resolve()}", file.parent, file.name)


def open_storage(where: Location, study_name: str) -> BaseStorage:
    """Optuna's storage at ``where``, once a file there has been read and found usable."""
    if where.file is not None:
        names = journal_studies(where.file) if where.kind == "journal" else sqlite_studies(where.file)
        if names and study_name not in names:
            raise other_studies(where, names, study_name)
        where.file.parent.mkdir(parents=True, exist_ok=True)
    if where.kind == "journal":
        assert where.file is not None
        return JournalStorage(JournalFileBackend(str(where.file)))
    # SQLite: wait for another worker's write instead of failing with "database is locked"
    engine = {"connect_args": {"timeout": 120}} if where.url.startswith("sqlite") else {}
    try:
        return RDBStorage(where.url, engine_kwargs=engine)
    except Exception as e:  # a driver's or a schema's error: its first line is the reason
        raise StudyError(f"{where.shown()}: Optuna cannot open it: {first_line(e)}") from e


def sqlite_studies(file: Path) -> list[str]:
    """The names of the studies in an Optuna SQLite file, read without writing; [] for a missing
    or empty file (a new study). Raises StudyError for a file that is not such a database."""
    if not file.exists() or file.stat().st_size == 0:
        return []
    with open(file, "rb") as f:
        if f.read(len(SQLITE_HEADER)) != SQLITE_HEADER:
            raise StudyError(
                f"{file} is not a SQLite database (corrupt, or another kind of file); move it away to start a new study"
            )
    try:
        with sqlite3.connect(f"file:{file.resolve()}?mode=ro", uri=True) as db:
            check = db.execute("PRAGMA quick_check").fetchone()[0]
            if check != "ok":
                raise StudyError(f"{file} is a corrupt SQLite database ({check})")
            tables = {row[0] for row in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
            if not tables:
                return []
            if not {"studies", "trials", "version_info"} <= tables:
                raise StudyError(
                    f"{file} is a SQLite database but not an Optuna study's (tables: {', '.join(sorted(tables))})"
                )
            return [row[0] for row in db.execute("SELECT study_name FROM studies ORDER BY study_id")]
    except sqlite3.DatabaseError as e:
        raise StudyError(f"{file} is a corrupt SQLite database ({first_line(e)})") from e


def journal_studies(file: Path) -> list[str]:
    """The names of the studies an Optuna journal file created, read without writing; [] for a
    missing or empty file. Every line must be one JSON operation, the last one ended too (an
    unfinished last line would be glued to the next write)."""
    if not file.exists() or file.stat().st_size == 0:
        return []
    names = []
    with open(file, "rb") as f:
        for number, line in enumerate(f, start=1):
            try:
                operation = json.loads(line)
                if not line.endswith(b"\n") or not isinstance(operation, dict) or "op_code" not in operation:
                    raise ValueError("not a whole operation")
            except ValueError as e:
                raise StudyError(
                    f"{file} is not a readable Optuna journal: line {number} is not one of its operations ({first_line(e)})"
                ) from e
            if operation["op_code"] == 0 and str(operation.get("study_name")) not in names:  # CREATE_STUDY
                names.append(str(operation.get("study_name")))
    return names


def other_studies(where: Location, names: list[str], study_name: str) -> StudyError:
    """The refusal of a file that holds other studies than ``study_name``."""
    held = ", ".join(f"'{n}'" for n in names)
    return StudyError(
        f"{where.shown()} holds another study ({held}), not '{study_name}': give another hydra.sweep.dir "
        f"(or hydra.sweeper.study_name={names[0]} to continue that one)"
    )


def open_study(storage: BaseStorage, where: Location, name: str, direction: str, identity: dict) -> optuna.Study:
    """The study ``name``: created with ``identity`` when new, else loaded and checked to be the same
    search in the same direction (StudyError naming the differences when it is not)."""
    names = optuna.study.get_all_study_names(storage)
    if name not in names:
        study = optuna.create_study(storage=storage, study_name=name, direction=StudyDirection[direction.upper()])
        study.set_user_attr(IDENTITY, identity)
        return study
    study = optuna.load_study(study_name=name, storage=storage)
    stored = study.user_attrs.get(IDENTITY)
    n = len(study.get_trials(deepcopy=False))
    if stored is None and n:
        raise StudyError(f"{where.shown()} holds study '{name}' with {n} trials that ferl's sweeper did not make")
    found = [] if stored is None else differences(stored, identity)
    if study.direction.name.lower() != direction:
        found.insert(0, f"direction {study.direction.name.lower()} there, {direction} here")
    if found:
        raise StudyError(
            f"{where.shown()} holds study '{name}' ({n} trials) of another search: {'; '.join(found)}; "
            "run that search to continue it, or give another hydra.sweep.dir"
        )
    if stored is None:
        study.set_user_attr(IDENTITY, identity)
    return study


def differences(stored: dict, identity: dict) -> list[str]:
    """What differs between a stored search and this one, key by key."""
    there, here = stored.get("space", {}), identity["space"]
    found = [
        f"{key}: {described(there[key]) if key in there else 'not searched'} there, "
        f"{described(here[key]) if key in here else 'not searched'} here"
        for key in sorted(set(there) | set(here))
        if there.get(key) != here.get(key)
    ]
    fixed_there, fixed_here = set(stored.get("overrides", [])), set(identity["overrides"])
    if fixed_there != fixed_here:
        found.append(
            f"overrides {' '.join(sorted(fixed_there - fixed_here)) or '(none)'} there, "
            f"{' '.join(sorted(fixed_here - fixed_there)) or '(none)'} here"
        )
    return found


def first_line(e: BaseException) -> str:
    return (str(e).strip().splitlines() or [type(e).__name__])[0]


@contextmanager
def claims(where: Location) -> Iterator[None]:
    """Hold the study's claims lock: one process at a time looks at the trials and changes who runs what."""
    where.home.mkdir(parents=True, exist_ok=True)
    fd = os.open(where.claims_file, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # drops the flock


class Worker:
    """This process as the study's other workers see it: a file in ``.<file>.workers/`` that it
    keeps flocked while it lives; its name is written on every trial the process runs."""

    def __init__(self, folder: Path) -> None:
        folder.mkdir(parents=True, exist_ok=True)
        self.folder = folder
        self.name = f"{socket.gethostname()}-{os.getpid()}-{secrets.token_hex(3)}"
        self.fd: int | None = os.open(folder / self.name, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)

    def alive(self, name: str | None) -> bool:
        """Whether the worker ``name`` still runs; a dead one's file is removed (under the claims lock)."""
        if name == self.name:
            return True
        if not name:
            return False  # a trial claimed by a process that died before it wrote its name
        try:
            fd = os.open(self.folder / name, os.O_RDONLY | os.O_CLOEXEC)
        except FileNotFoundError:
            return False
        try:
            if flock_taken(fd):
                return True
        finally:
            os.close(fd)
        (self.folder / name).unlink(missing_ok=True)
        return False

    def close(self) -> None:
        """Leave: remove the file, then drop the flock."""
        if self.fd is not None:
            (self.folder / self.name).unlink(missing_ok=True)
            os.close(self.fd)
            self.fd = None
