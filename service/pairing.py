"""Pairing a second screen: a short one-time code that buys the access token.

A tablet or a restarted browser has no start-up URL with ``?token=``, and typing a 32-character
token on a shop floor is what nobody does. The server keeps one pairing code at a time: six
digits, printed at start-up and shown on a signed-in pendant on request ("Pair a screen"). It is
good for one sign-in, for :data:`CODE_TTL_S`, and for :data:`MAX_WRONG_TRIES` wrong guesses; after
that it is void and a new one must be asked for. Six digits and five tries give a guesser one
chance in 200,000 per code.
"""

from __future__ import annotations

import hmac
import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

#: How long a pairing code is good for (s).
CODE_TTL_S = 600.0
#: Wrong codes after which the code is void.
MAX_WRONG_TRIES = 5
#: Digits of a code.
CODE_DIGITS = 6


@dataclass(frozen=True)
class Redeemed:
    """The outcome of a code given by a screen.

    Attributes
    ----------
    ok : bool
        The code was right: the screen gets the token, and the code is used up.
    reason : str
        Why not, in the operator's words ("" when ok).
    """

    ok: bool
    reason: str = ""


class Pairing:
    """The one pairing code of this server (thread-safe).

    Parameters
    ----------
    clock : callable returning float, optional
        Monotonic seconds (tests pass their own).
    """

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self._lock = threading.Lock()
        self._code: str | None = None
        self._expires_s = 0.0
        self._wrong = 0

    def issue(self) -> str:
        """A new code (the previous one is void from now on)."""
        code = f"{secrets.randbelow(10**CODE_DIGITS):0{CODE_DIGITS}d}"
        with self._lock:
            self._code, self._wrong = code, 0
            self._expires_s = self._clock() + CODE_TTL_S
        return code

    def expires_in_s(self) -> float:
        """Seconds the current code is still good for (0 when there is none)."""
        with self._lock:
            if self._code is None:
                return 0.0
            return max(0.0, self._expires_s - self._clock())

    def redeem(self, code: str) -> Redeemed:
        """Check a code; a right one is used up, a wrong one counts against the code."""
        with self._lock:
            if self._code is None:
                return Redeemed(False, "no pairing code is open (it was used, or voided)")
            if self._clock() >= self._expires_s:
                self._code = None
                return Redeemed(False, f"the pairing code expired ({CODE_TTL_S / 60:.0f} min)")
            if hmac.compare_digest(code.encode(), self._code.encode()):
                self._code = None
                return Redeemed(True)
            self._wrong += 1
            left = MAX_WRONG_TRIES - self._wrong
            if left <= 0:
                self._code = None
                return Redeemed(False, f"wrong code {MAX_WRONG_TRIES} times: the code is void")
            return Redeemed(False, f"wrong code ({left} tries left)")
