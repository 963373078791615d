"""The progress-bar protocol: the commands' tqdm bars count, resume and stay quiet on request."""
from __future__ import annotations

import pytest

from console.progress import counted, tqdm_bars


def test_tqdm_bars_count_from_the_initial_step(capsys: pytest.CaptureFixture) -> None:
    bar = tqdm_bars("step")(10, 4)
    bar.update(2)
    bar.set_description("render")
    bar.set_postfix_str("loss=0.1")
    assert bar.n == 6 and bar.total == 10
    bar.close()
    err = capsys.readouterr().err
    assert "render" in err and "6/10" in err and "loss=0.1" in err


def test_disabled_bars_draw_nothing(capsys: pytest.CaptureFixture) -> None:
    bar = tqdm_bars("scene", enabled=False)(3)
    bar.update(3)
    bar.close()
    assert capsys.readouterr().err == ""


def test_counted_draws_one_bar_from_done_and_total(capsys: pytest.CaptureFixture) -> None:
    """A render's ``(done, total)`` calls move one bar to ``done`` and close it at ``total``."""
    advance = counted(tqdm_bars("sample"), "render")
    for done in (3, 5, 10):
        advance(done, 10)
    err = capsys.readouterr().err
    assert "render: 100%" in err and "10/10" in err
    assert counted(None, "render") is None
