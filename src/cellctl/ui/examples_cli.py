"""``cellctl examples``: the examples that ship inside the package, listed or copied out.

The README's paths (``examples/robot/*.aml``, ``examples/cell-tending`` ...) are the
repository's; from an installed cellctl, ``cellctl examples copy`` puts the same files in
``./examples`` so those paths work in any directory. A copy is the user's: files 0644,
directories 0755, nothing existing overwritten, nothing written through a symbolic link.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from importlib import resources
from importlib.resources.abc import Traversable
from pathlib import Path

import click

from cellctl.errors import UsageError

#: Every example that ships (a directory of ``cellctl/examples``) and what it is: the one
#: table the listing prints and the copy copies (tests/test_examples_cli.py checks that it
#: names exactly the package's directories).
EXAMPLES: dict[str, str] = {
    "cell": "the lab's cell: an IBM 7545 robot, two Dyna 2400 mills, a PLC",
    "cell-modern": "the lab's cell, one mill a Fanuc-style CNC fed G-code by drip-feed",
    "cell-tending": "a UR5e cobot tending a Haas-style CNC and a Dyna 2400",
    "programs": "DYNALAN mill programs; broken/: one mistake a file (mill check)",
    "robot": "the lab cell's three AML/E transfer programs (robot compile)",
}

#: Where ``cellctl examples copy`` puts them unless told.
DEFAULT_DIR = "examples"
FILE_MODE = 0o644
DIR_MODE = 0o755
#: Open flags for a directory of the copy: never a link in its place.
_DIR_FLAGS = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC
#: Open flags for a file of the copy: made here, never one that exists, never through a link.
_FILE_FLAGS = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC


def shipped(name: str) -> Traversable:
    """Example ``name`` as the installed package holds it."""
    return resources.files("cellctl").joinpath("examples", name)


def _entries(folder: Traversable) -> Iterator[Traversable]:
    """``folder``'s entries by name, without hidden files and byte-code caches."""
    for entry in sorted(folder.iterdir(), key=lambda e: e.name):
        if not entry.name.startswith(".") and entry.name != "__pycache__":
            yield entry


def _exists(path: Path) -> bool:
    """Whether anything is at ``path``, a link (even a broken one) included."""
    try:
        path.lstat()
    except FileNotFoundError:
        return False
    return True


def check_target(directory: Path, names: list[str]) -> None:
    """Refuse (:class:`UsageError`, naming the path) before anything is written: a
    ``directory`` that is a link or not a directory, or an example already there."""
    if directory.is_symlink():
        raise UsageError(
            f"{directory}: a symbolic link (to {os.readlink(directory)}): the examples are "
            "copied through no link: name a directory of its own"
        )
    if _exists(directory) and not directory.is_dir():
        raise UsageError(f"{directory}: not a directory: name another to copy the examples to")
    for name in names:
        if _exists(directory / name):
            raise UsageError(
                f"{directory / name} exists: nothing copied (a copy never overwrites): "
                "move it away, or copy to another directory"
            )


def _copy_tree(source: Traversable, parent_fd: int, name: str) -> int:
    """Make directory ``name`` in the open directory ``parent_fd`` and copy ``source``'s
    files into it (0644, directories 0755): the number of files copied."""
    os.mkdir(name, DIR_MODE, dir_fd=parent_fd)
    fd = os.open(name, _DIR_FLAGS, dir_fd=parent_fd)
    try:
        os.fchmod(fd, DIR_MODE)  # whatever the umask: the user's copy
        copied = 0
        for entry in _entries(source):
            if entry.is_dir():
                copied += _copy_tree(entry, fd, entry.name)
            elif entry.is_file():
                out = os.open(entry.name, _FILE_FLAGS, FILE_MODE, dir_fd=fd)
                with os.fdopen(out, "wb") as f:
                    os.fchmod(f.fileno(), FILE_MODE)
                    f.write(entry.read_bytes())
                copied += 1
        return copied
    finally:
        os.close(fd)


def copy_examples(directory: Path, names: list[str]) -> int:
    """Copy examples ``names`` into ``directory`` (made if missing) as ``directory/NAME``:
    the number of files copied. Refused before anything is written if one is there already
    (:func:`check_target`); nothing is written through a link."""
    check_target(directory, names)
    made = not _exists(directory)
    try:
        if made:
            directory.mkdir(parents=True, mode=DIR_MODE)
        top = os.open(directory, _DIR_FLAGS)
    except OSError as e:
        raise UsageError(f"{directory}: cannot copy the examples there: {e.strerror}") from None
    try:
        if made:
            os.fchmod(top, DIR_MODE)  # whatever the umask: the user's copy
        return sum(_copy_tree(shipped(name), top, name) for name in names)
    except FileExistsError as e:  # made between the check and the copy: still never replaced
        raise UsageError(f"{directory}: {e.filename} appeared while copying: stopped") from None
    except OSError as e:
        raise UsageError(f"{directory}: copying stopped: {e.strerror}") from None
    finally:
        os.close(top)


@click.group("examples", invoke_without_command=True)
@click.pass_context
def examples_group(ctx: click.Context) -> None:
    """List the examples that ship with cellctl, or copy them: `examples copy DIR`.

    The README's tour names files under examples/; from an installed cellctl, `cellctl
    examples copy` puts them in ./examples, so its commands work in any directory.
    """
    if ctx.invoked_subcommand is not None:
        return
    width = max(len(name) for name in EXAMPLES) + 2
    for name, what in EXAMPLES.items():
        click.echo(f"{name:<{width}}{what}")


@examples_group.command("copy")
@click.argument("directory", default=DEFAULT_DIR, type=click.Path(path_type=Path))
@click.option(
    "--only",
    "only",
    multiple=True,
    type=click.Choice(list(EXAMPLES)),
    help="Copy this example alone (repeat for more); default: all of them.",
)
def copy_command(directory: Path, only: tuple[str, ...]) -> None:
    """Copy the examples into DIRECTORY (default ./examples), each as DIRECTORY/NAME.

    Nothing that exists is overwritten: an example already there refuses the whole copy
    before anything is written. Files are made 0644 and directories 0755, as your own.
    """
    names = list(dict.fromkeys(only)) or list(EXAMPLES)
    copied = copy_examples(directory, names)
    click.echo(f"copied {copied} files to {directory}: {', '.join(names)}")
