"""A user's own plugin, outside dider: what a checkpoint may build once the user trusts it."""

from __future__ import annotations

from dider.models.encoder import GNNLSTMEncoder


class MyEncoder(GNNLSTMEncoder):
    """DNRI's encoder under another name, as a user's package would hold one."""


def not_a_class(**settings):  # a function at a class's place: never built, even when trusted
    raise AssertionError("called")
