"""Checks of an explanation before it is modelled (``diagnose/_checks.py``)."""


def test_shift_window_at_the_edge_of_the_scan():
    """A window starting in the first or ending in the last time bin is at the edge (where a
    drift's residual ramp is largest once the pose takes up its mean)."""
    from types import SimpleNamespace

    import numpy as np

    from hartrao_jax.diagnose._checks import _at_edge

    edges = np.linspace(0.0, 11.0, 111)  # 0.1 s bins
    for window, edge in (((0.0, 0.3), True), ((0.05, 1.0), True), ((10.5, 0.45), True),
                         ((4.0, 0.6), False), ((0.3, 0.6), False), (None, False)):
        sc = SimpleNamespace(window_s=window, search={"edges": edges})
        assert _at_edge(sc) is edge, window
    assert _at_edge(SimpleNamespace(window_s=(0.0, 0.3), search={})) is False


def test_ambiguous_choice_is_said_in_the_explanation():
    """Two candidates the data hardly tell apart: the finding's sentence names the other with
    the likelihood ratio the choice rests on."""
    from hartrao_jax.diagnose._checks import AMBIGUOUS_LIKELIHOOD_RATIO
    from hartrao_jax.diagnose._diagnose import _ambiguity

    s = _ambiguity("x1n", [{"effect": "x5n", "correlation": -0.9857, "likelihood_ratio": 1.884}])
    assert s == ("The data hardly tell it apart from x5n (correlation -0.986, likelihood ratio "
                 "1.88 in favour of x1n): the choice rests on that ratio alone.")
    assert AMBIGUOUS_LIKELIHOOD_RATIO == 20.0
