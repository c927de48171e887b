"""Text from elsewhere shown on a terminal, or written to a CSV file: a driver's error, a remote device's reason,
an operator's words.

Written raw, a control character in it would act on the terminal: ``ESC [2J`` clears the screen, ``ESC ]0;``
retitles the window, ``CR`` overwrites the line it is on, a bidirectional override reorders what follows.
``printable`` shows each as its escape (``\\x1b``) instead; newlines and tabs stay. In a CSV cell, text starting
with =, +, -, @, a tab or a carriage return runs as a formula when a spreadsheet opens the file: ``inert`` puts a '
before it. A file named in a command a person is told to run is a ``shell_word``: `rerun 'r #1.rrd'`, pasted as it
is shown, opens that file.
"""

from __future__ import annotations

import shlex

_ESCAPED = {c: f"\\x{c:02x}" for c in (*range(0x20), 0x7F, *range(0x80, 0xA0)) if chr(c) not in "\n\t"}
_ESCAPED |= {c: f"\\u{c:04x}" for c in (*range(0x202A, 0x202F), *range(0x2066, 0x206A))}


def printable(text: str) -> str:
    return text.translate(_ESCAPED)


def inert(value: object) -> object:
    """A CSV cell a spreadsheet shows and does not run (OWASP's advice for CSV); numbers, and text that reads as
    one (-0.5), as they are."""
    if isinstance(value, str) and value[:1] in ("=", "+", "-", "@", "\t", "\r"):
        try:
            float(value)
        except ValueError:
            return "'" + value
    return value


def shell_word(value: object) -> str:
    """``value`` as one word of a shell command: as it is, or quoted where it has a space, '#', '?', a quote..."""
    return shlex.quote(str(value))
