"""Numbers in the library's messages and reports."""

from __future__ import annotations

__all__ = ["signed"]


def signed(value: float, digits: int = 3) -> str:
    """``value`` with its sign and ``digits`` decimals, as ``f"{value:+.{digits}f}"`` writes
    it, except that a value which rounds to zero reads ``+0.000``, never ``-0.000`` (a gap of
    -0.0002 is no gap, and a minus sign would say which way it went).

    Example:
        >>> signed(-0.0002), signed(-0.0123), signed(0.5, 2)
        ('+0.000', '-0.012', '+0.50')
    """
    text = f"{float(value):+.{digits}f}"
    return "+" + text[1:] if float(text) == 0 else text
