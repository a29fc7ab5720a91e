"""Client tokens people cannot get wrong: made strong, stored private, refused when weak.

- ``new_token()``: 256 random bits as 43 URL-safe characters (``secrets.token_urlsafe(32)``).
- ``check_token(token)``: raise ``WeakToken`` unless ``zxcvbn`` (Dropbox's password-strength
  estimator, the ``zxcvbn`` package on PyPI) estimates that guessing it takes at least
  ``10 ** MIN_GUESSES_LOG10`` guesses. zxcvbn models what crackers try first — dictionary words,
  names, keyboard walks, repeats (``Password1!Password1!Pa`` ≈ 10^6.9 guesses), l33t, dates —
  and rates random text at 10 guesses per character, so a random token needs ≥ 20 characters.
  Every place that accepts a token (the CLI, ``ControlClient``, ``acquire token``,
  ``derive_credentials``) calls it.
- ``write_token_file(path, token, force)``: create the file with mode 0600 (never through a
  wider mode), refusing to overwrite without ``force``.
- ``read_token_file(path)``: the token, refusing a file that the group or others may read or
  write (as ssh refuses an unprotected private key) and a weak token.

Why 10^20 guesses: a token's only use to an attacker is offline guessing against one captured
SCRAM exchange (or a leaked StoredKey), one PBKDF2-HMAC-SHA256 of the configured iteration
count per guess. The weakest a configuration may hold is ``control_auth.MIN_ITERATIONS`` = 4096
(RFC 7677); at 600 000 iterations a high-end GPU manages < 10 000 guesses/s (tobtu.com's
minimum-settings table, RTX 4090), i.e. ~1.5 million guesses/s at 4096. 10^20 guesses then cost
~1 million GPU-years on average at 4096 iterations (~150 million at the default 600 000): out of
reach of anyone who would attack a robot cell. The issue's token (10^6.9) fell in 3.2 s.
"""

from __future__ import annotations

import functools
import os
import secrets
import stat
from pathlib import Path

#: Guesses (log10) zxcvbn must estimate for a token to be accepted (see the module docstring).
MIN_GUESSES_LOG10 = 20.0

#: Fewest characters of a token: zxcvbn rates n random characters at most 10^n guesses, so a
#: shorter token can never reach ``MIN_GUESSES_LOG10``.
MIN_TOKEN_CHARS = 20

#: Longest accepted token (characters).
MAX_TOKEN_CHARS = 1024

#: Characters zxcvbn looks at (its own limit; its running time grows with the length). A longer
#: token is judged by its head: never rated stronger than it is.
ESTIMATE_CHARS = 72

#: Words a cell's token must not be built from (zxcvbn's user inputs): the product's own names.
PRODUCT_WORDS = ("remaster", "acquire", "operator", "token", "daemon", "station", "cell", "robot", "viewer")

#: Where ``acquire token new`` writes by default, and what the CLI's examples name.
DEFAULT_TOKEN_PATH = Path("~/.config/remaster/token")


class WeakToken(ValueError):
    """A token too short or too predictable to stand against offline guessing."""


class TokenFileError(ValueError):
    """A token file that cannot be used (missing, unprotected, or holding a weak token)."""


def new_token() -> str:
    """256 random bits as 43 URL-safe characters."""
    return secrets.token_urlsafe(32)


@functools.lru_cache(maxsize=16)  # a client checks its token once per exchange
def guesses_log10(token: str, context: tuple[str, ...] = ()) -> float:
    """zxcvbn's estimate of the guesses (log10) an attacker needs for ``token`` (its first
    ``ESTIMATE_CHARS`` characters), knowing the product's words and ``context`` (client name,
    cell id, …)."""
    from zxcvbn import zxcvbn  # ~50 ms of word lists: loaded by the first check only

    words = [w for w in (*PRODUCT_WORDS, *context) if w]
    return float(zxcvbn(token[:ESTIMATE_CHARS], user_inputs=words, max_length=ESTIMATE_CHARS)["guesses_log10"])


def check_token(token: str, context: tuple[str, ...] = ()) -> str:
    """``token`` when it may be used; WeakToken saying what is wrong and what to do otherwise.

    context: words the attacker knows besides the product's own (the client's name, the cell id).
    """
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
                        f"(10^{MIN_GUESSES_LOG10:g} guesses); {fix}")
    estimate = guesses_log10(token, context)
    if estimate < MIN_GUESSES_LOG10:
        raise WeakToken(f"token too weak: guessable in about 10^{estimate:.1f} tries (zxcvbn), at least "
                        f"10^{MIN_GUESSES_LOG10:g} needed against offline guessing; {fix}")
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
