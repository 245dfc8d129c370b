"""``hydrosoft-stack keys generate DIR --host NAME``: a host's CURVE key pair for a stack split across hosts.

Writes ``DIR/NAME.key`` (the public key, to copy into every peer's ``curve.authorized_keys_dir``) and
``DIR/NAME.key_secret`` (the secret key, mode 0600: it never leaves the host) as ``zmq.auth`` certificates. The
files are created under umask 077, so the secret is never readable by others, not even for a moment. An existing
pair is never overwritten (a replaced key locks every peer out until its public half is copied again): exit 2.
"""

from __future__ import annotations

import argparse
import os
import re
import sys
from pathlib import Path

import zmq.auth

#: A host name as the config's ``[hosts.NAME]`` writes it: letters, digits, ``-`` and ``_``.
HOST_NAME = re.compile(r"[A-Za-z0-9_-]{1,64}")
#: Mode of the secret key file: read and write for its owner only.
SECRET_KEY_MODE = 0o600

EXIT_OK = 0
EXIT_FAILED = 2


class KeyPairError(ValueError):
    """A key pair that cannot be written; the text says why."""


def generate_key_pair(directory: Path, host: str) -> tuple[Path, Path]:
    """Write host ``host``'s key pair in ``directory`` (created, mode 0700); return ``(public, secret)`` file
    paths. Raises KeyPairError for a bad host name or a pair that already exists."""
    if not HOST_NAME.fullmatch(host):
        raise KeyPairError(f"--host {host!r}: a host name is 1-64 letters, digits, '-' or '_'")
    public, secret = directory / f"{host}.key", directory / f"{host}.key_secret"
    for path in (public, secret):
        if path.exists():
            raise KeyPairError(f"{path} exists; remove it first to replace {host}'s keys (every peer then needs the "
                            "new public key)")
    old_umask = os.umask(0o077)
    try:
        directory.mkdir(parents=True, exist_ok=True)
        written = zmq.auth.create_certificates(directory, host)
    finally:
        os.umask(old_umask)
    os.chmod(secret, SECRET_KEY_MODE)
    os.chmod(public, 0o644)
    return Path(written[0]), Path(written[1])


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments: DIR --host NAME."""
    parser.add_argument("directory", metavar="DIR", help="where to write NAME.key and NAME.key_secret")
    parser.add_argument("--host", required=True, help="the host's name, as in the config's [hosts.NAME]")


def run(args: argparse.Namespace) -> int:
    """Run ``hydrosoft-stack keys generate``; the exit code (0 written, 2 refused)."""
    try:
        public, secret = generate_key_pair(Path(args.directory), args.host)
    except (KeyPairError, OSError) as error:
        print(f"hydrosoft-stack keys generate: {error}", file=sys.stderr)
        return EXIT_FAILED
    print(f"wrote {public} (copy it into every peer's curve.authorized_keys_dir) and {secret} (mode 0600; it stays "
          "on this host)")
    return EXIT_OK
