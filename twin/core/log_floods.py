"""A flood of one kind of message said in the log: the first ten, then every thousandth, each with its count."""


def said(n: int) -> bool:
    """Whether the ``n``-th (from 1) of a flood is said in the log."""
    return n <= 10 or n % 1000 == 0
