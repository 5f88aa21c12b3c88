"""Files written whole or not at all, and JSON files of dataclass fields.

The lowest layer of jtus's I/O: datasets (``jtus.data``), checkpoints
(``jtus.checkpoint``), exports and the CLIs write through ``atomic_path``, so an
error or an interrupt never leaves a half-written file where a reader expects one.
"""

from __future__ import annotations

import contextlib
import dataclasses
import difflib
import json
import os
import shutil
import tempfile
import warnings


class UnknownKeyWarning(UserWarning):
    """A key that a jtus file format does not define; it is ignored. The command-line
    tools print it as one ``warning:`` line; ``warnings.simplefilter("error",
    UnknownKeyWarning)`` makes it an exception in code that calls jtus."""


def drop_unknown_keys(where, data, fields, what="key"):
    """``data`` without the keys that are not in ``fields``, warning once per dropped key
    with ``where`` (the file and object), ``what`` the key is, the key, the nearest
    known key when one is close (a likely misspelling) and the keys that are known."""
    fields = sorted(fields)
    unknown = [k for k in data if k not in fields]
    for k in unknown:
        near = difflib.get_close_matches(str(k), fields, n=1)
        hint = f" (did you mean {near[0]!r}?)" if near else ""
        warnings.warn(f"{where}: unknown {what} {k!r} ignored{hint}; expected some of {fields}",
                      UnknownKeyWarning, stacklevel=3)
    return {k: v for k, v in data.items() if k not in unknown}


@contextlib.contextmanager
def atomic_path(path, suffix=".tmp"):
    """Yield a temporary path beside ``path``; rename it onto ``path`` on success and
    delete it on any failure (including KeyboardInterrupt). ``suffix`` ends the
    temporary name (a writer that picks its format by extension needs its own)."""
    path = os.fspath(path)
    d = os.path.dirname(os.path.abspath(path))
    os.makedirs(d, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=os.path.basename(path) + ".", suffix=suffix, dir=d)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; give the file ordinary permissions
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        raise


def read_json_fields(path, cls, what):
    """A JSON file holding one object whose keys are fields of dataclass ``cls``:
    the dict without keys that are not fields (each warned about, naming ``path`` and the
    key: ``drop_unknown_keys``), or ``ValueError`` naming ``path`` (invalid JSON, not an
    object; ``what`` names the kind of key in messages, e.g. "config key")."""
    if os.path.isdir(path):
        raise ValueError(f"{path}: is a folder; expected a JSON file")
    try:
        with open(path, encoding="utf-8") as fh:
            data = json.load(fh)
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: not a UTF-8 text file, so not JSON ({e.reason} at byte "
                         f"{e.start})") from e
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: not valid JSON ({e})") from e
    fields = {f.name for f in dataclasses.fields(cls)}
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object of {cls.__name__} keys")
    return drop_unknown_keys(path, data, fields, what)


def _existing_parent(path):
    """The nearest folder above ``path`` that exists (where it would be created)."""
    parent = os.path.dirname(os.path.abspath(path))
    while not os.path.exists(parent):
        parent = os.path.dirname(parent)
    return parent


def _writable_parent(path, field):
    parent = _existing_parent(path)
    if not os.path.isdir(parent):
        raise ValueError(f"{field}: {parent} is a file, so {path} cannot be created")
    if not os.access(parent, os.W_OK):
        raise ValueError(f"{field}: {parent} is not writable")
    try:  # access() says yes to root on /proc and read-only mounts: try a file there
        fd, probe = tempfile.mkstemp(prefix=".jtus-probe-", dir=parent)
    except OSError as e:
        raise ValueError(f"{field}: no file can be created in {parent} ({e.strerror})") from e
    os.close(fd)
    os.remove(probe)


def check_out_file(path, force=True, field="--out", kind="file"):
    """Refuse, before any work starts, an output path that cannot take a file: an
    existing folder, an existing file without ``force``, a parent that is a file or
    is not writable. ``ValueError`` naming ``field``."""
    path = os.fspath(path)
    if os.path.isdir(path):
        raise ValueError(f"{field}: {path} is a folder; expected {kind} path")
    if os.path.exists(path) and not force:
        raise ValueError(f"{field}: {path} exists; pass --force to replace it")
    _writable_parent(path, field)


def check_out_folder(path, field="--out"):
    """Refuse, before any work starts, an output folder that is a file or cannot be
    created."""
    path = os.fspath(path)
    if os.path.exists(path) and not os.path.isdir(path):
        raise ValueError(f"{field}: {path} is a file; expected a folder")
    if not os.path.exists(path):
        _writable_parent(path, field)


def available_memory():
    """Bytes of memory this machine has free now (``MemAvailable``), or None."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def check_budget(memory, disk, out, force=False, what="this command",
                 smaller="smaller sizes or fewer frames"):
    """Refuse, before any work, a command whose ``memory`` (bytes held at once) or
    ``disk`` (bytes written under ``out``'s folder) exceeds what the machine has, unless
    ``force``; ``smaller`` says what to reduce. ``ValueError`` saying how much is
    needed and how much there is."""
    if force:
        return
    gib = 2.0 ** 30
    free_mem = available_memory()
    if free_mem is not None and memory > free_mem:
        raise ValueError(f"{what} needs about {memory / gib:.1f} GiB of memory, and "
                         f"{free_mem / gib:.1f} GiB are free; use {smaller}, or pass --force "
                         "to try anyway")
    folder = _existing_parent(out)
    free_disk = shutil.disk_usage(folder).free
    if disk > free_disk:
        raise ValueError(f"{what} writes about {disk / gib:.1f} GiB, and {folder} has "
                         f"{free_disk / gib:.1f} GiB free; pass --force to try anyway")
