"""How the fake Sunrise scores a client's answers: receive windows, streaks and connection quality.

A *window* is ``receive_multiplier`` consecutive monitoring messages; the client must answer one
message of each window before the window's last message is followed by the next. An answer
reflecting an older message is *late*; a window without a timely answer is *missed*. Quality is
taken over the last ``quality_window`` windows: no miss EXCELLENT, up to 10 % GOOD, up to 30 %
FAIR, else POOR.
"""

from __future__ import annotations

from collections import deque

from drivers.kuka_fri.messages import ConnectionQuality


class AnswerWindows:
    """The controller's record of answered and missed windows.

    ``answered``: the current window has its answer; ``first_seq``: the first counter sent in
    the current window (answers reflecting an older one are late); ``since_applied``: windows
    since the last set-point was taken (the speed check spans them); ``consecutive_missed`` /
    ``consecutive_good``: the running streaks (``consecutive_good`` −1 marks a bad answer that
    restarts the count).
    """

    def __init__(self, receive_multiplier: int, quality_window: int) -> None:
        self.receive_multiplier = receive_multiplier
        self.answered = False
        self.first_seq = 0
        self.since_applied = 1
        self.consecutive_missed = 0
        self.consecutive_good = 0
        self._count = 0
        self._missed: deque[bool] = deque(maxlen=quality_window)

    def quality(self) -> ConnectionQuality:
        """Connection quality over the last windows; POOR before the first one closes."""
        if not self._missed:
            return ConnectionQuality.POOR
        miss = sum(self._missed) / len(self._missed)
        if miss == 0:
            return ConnectionQuality.EXCELLENT
        if miss <= 0.1:
            return ConnectionQuality.GOOD
        if miss <= 0.3:
            return ConnectionQuality.FAIR
        return ConnectionQuality.POOR

    def message_due(self) -> bool:
        """Count one controller cycle; True when it ends a window (then call ``close`` or
        ``skip``, and ``open(seq)``)."""
        self._count += 1
        if self._count < self.receive_multiplier:
            return False
        self._count = 0
        return True

    def open(self, seq: int) -> None:
        """A new window starts with the message numbered ``seq``."""
        self.first_seq = seq

    def skip(self) -> None:
        """A window with no session (IDLE): not scored."""
        self.answered = False

    def close(self) -> bool:
        """Score the window that ends; returns whether it was missed."""
        missed = not self.answered
        self._missed.append(missed)
        self.since_applied += 1
        if missed:
            self.consecutive_missed += 1
            self.consecutive_good = 0
        else:
            self.consecutive_missed = 0
            self.consecutive_good += 1
        self.answered = False
        return missed

    def forget(self) -> None:
        """A controller restart: no history, no streaks."""
        self._missed.clear()
        self.consecutive_good = self.consecutive_missed = 0
