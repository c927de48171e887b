"""Messages the lab refuses (``message.invalid``: not decodable; ``message.rejected``: without the attempt's
provenance) come one by one from a device with a bug, or by the hundred thousand from a flood: a device whose every
telemetry reading fails validation, at 10 a second, made 864,000 journal rows a day, each with its excerpt. Each is
counted; the journal notes the first ``FULL`` of each kind one by one, then one row in ``EVERY``, which says how
many it stands for. A live campaign's input journal holds each sender's undecodable messages of a batch as one entry
with their count (``twin.campaign.replay.encode_all``), a lab of several campaigns a run of them from one sender."""

from __future__ import annotations

FULL = 1_000  # refusals of one kind noted one by one
EVERY = 1_000  # after them, one row in this many


def left_out(before: int, after: int) -> int | None:
    """The row for refusals ``before + 1 .. after`` of one kind (one, live; a journalled run of them, replayed):
    None if they get none, else how many refusals it stands for beyond its own (0: just itself)."""
    if after <= FULL:
        return 0
    if before >= FULL and (after - FULL) // EVERY == (before - FULL) // EVERY:
        return None
    return EVERY - 1 if before >= FULL else 0
