"""Client tokens people cannot get wrong: made strong, stored private, refused when weak.

- ``new_token()``: 256 random bits as 43 URL-safe characters (``secrets.token_urlsafe(32)``).
- ``check_token(token)``: raise ``WeakToken`` unless the token could hold ≥ 128 bits of entropy
  (at least ``MIN_TOKEN_CHARS`` characters, a character-set estimate ≥ 128 bits, enough distinct
  characters, not words of one case joined by separators). Every place that accepts a token
  (the CLI, ``ControlClient``, ``acquire token``) calls it. An estimate from the text cannot
  prove randomness; it refuses what is certainly weak (``dragon2024``, ``operator-secret``).
- ``write_token_file(path, token, force)``: create the file with mode 0600 (never through a
  wider mode), refusing to overwrite without ``force``.
- ``read_token_file(path)``: the token, refusing a file that the group or others may read or
  write (as ssh refuses an unprotected private key) and a weak token.
"""

from __future__ import annotations

import math
import os
import secrets
import stat
import string
from pathlib import Path

#: Fewest characters of a token (22 URL-safe characters hold 132 bits).
MIN_TOKEN_CHARS = 22

#: Entropy a token's character-set estimate must reach (bits).
MIN_TOKEN_BITS = 128

#: Longest accepted token (characters).
MAX_TOKEN_CHARS = 1024

#: Where ``acquire token new`` writes by default, and what the CLI's examples name.
DEFAULT_TOKEN_PATH = Path("~/.config/remaster/token")


class WeakToken(ValueError):
    """A token too short or too predictable to stand against offline guessing."""


class TokenFileError(ValueError):
    """A token file that cannot be used (missing, unprotected, or holding a weak token)."""


def new_token() -> str:
    """256 random bits as 43 URL-safe characters."""
    return secrets.token_urlsafe(32)


def estimated_bits(token: str) -> float:
    """Length × log2(size of the character classes used): an upper bound of the entropy."""
    pool = 0
    classes = (string.ascii_lowercase, string.ascii_uppercase, string.digits)
    for cls in classes:
        if any(c in cls for c in token):
            pool += len(cls)
    if any(not any(c in cls for cls in classes) for c in token):
        pool += 32  # punctuation and the rest
    return len(token) * math.log2(pool) if pool else 0.0


def check_token(token: str) -> str:
    """``token`` when it may be used; WeakToken saying what is wrong and what to do otherwise."""
    fix = "make one with `acquire token new` (256 random bits)"
    if not isinstance(token, str) or not token:
        raise WeakToken(f"no token given; {fix}")
    if token != token.strip() or any(c.isspace() or not c.isprintable() for c in token):
        raise WeakToken(f"a token may not contain spaces or control characters; {fix}")
    n = len(token)
    if n > MAX_TOKEN_CHARS:
        raise WeakToken(f"a token may have at most {MAX_TOKEN_CHARS} characters, given {n}")
    if n < MIN_TOKEN_CHARS:
        raise WeakToken(f"token too short: {n} characters, at least {MIN_TOKEN_CHARS} needed "
                        f"(≥ {MIN_TOKEN_BITS} bits); {fix}")
    bits = estimated_bits(token)
    if bits < MIN_TOKEN_BITS:
        raise WeakToken(f"token too weak: at most {bits:.0f} bits from its {n} characters, at least "
                        f"{MIN_TOKEN_BITS} needed; {fix}")
    if len(set(token)) < 8:
        raise WeakToken(f"token too repetitive: {len(set(token))} distinct characters; {fix}")
    words = token.replace("-", " ").replace("_", " ").replace(".", " ").split()
    if all(w.isalpha() and (w.islower() or w.isupper()) for w in words):
        raise WeakToken(f"token looks like words (letters of one case and separators only): guessable "
                        f"from a word list; {fix}")
    return token


def write_token_file(path: Path, token: str, *, force: bool = False) -> Path:
    """Write ``token`` (and a newline) to ``path`` with mode 0600; its folder is made 0700.

    Raises FileExistsError when ``path`` exists and ``force`` is false.
    """
    check_token(token)
    path = Path(path).expanduser()
    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    flags = os.O_WRONLY | os.O_CREAT | os.O_NOFOLLOW | (os.O_TRUNC if force else os.O_EXCL)
    fd = os.open(path, flags, 0o600)
    try:
        os.fchmod(fd, 0o600)  # an existing file overwritten with --force keeps no wider mode
        os.write(fd, (token + "\n").encode())
    finally:
        os.close(fd)
    return path


def unprotected(mode: int) -> bool:
    """True when a file of ``mode`` can be read or written by its group or others."""
    return bool(mode & (stat.S_IRWXG | stat.S_IRWXO))


def read_token_file(path: Path) -> str:
    """The token in ``path`` (surrounding white space stripped); TokenFileError when the file
    cannot be read, is readable or writable by group or others, or holds a weak token."""
    path = Path(path).expanduser()
    try:
        st = os.stat(path)
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise TokenFileError(f"cannot read token file {path}: {getattr(exc, 'strerror', None) or exc}") from exc
    if unprotected(st.st_mode):
        raise TokenFileError(
            f"UNPROTECTED TOKEN FILE: {path} has mode {stat.S_IMODE(st.st_mode):04o}; it must be readable by "
            f"you only. Run: chmod 600 {path} — and, since others could read it, make a new token with "
            "`acquire token new --force` and update the daemon's configuration.")
    try:
        return check_token(text.strip())
    except WeakToken as exc:
        raise TokenFileError(f"token file {path}: {exc}") from exc
