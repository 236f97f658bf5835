"""The README's Tour is executed here, so it cannot rot."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

README = Path(__file__).resolve().parents[1] / "README.md"

pytestmark = pytest.mark.usefixtures("fast_compilation")


def tour_code() -> str:
    """The first ```python block under the README's '## Tour' heading."""
    text = README.read_text(encoding="utf-8")
    section = text.split("\n## Tour", 1)
    assert len(section) == 2, "README.md has no '## Tour' section"
    body = re.split(r"\n## ", section[1], maxsplit=1)[0]
    match = re.search(r"```python\n(.*?)\n```", body, flags=re.S)
    assert match, "the README Tour has no ```python block"
    return match.group(1)


@pytest.mark.standard_dtypes  # the README code is user code: JAX's default promotion, optax.adam
def test_readme_tour_trains_and_samples(capsys):
    namespace: dict = {"__name__": "readme_tour"}
    exec(compile(tour_code(), "README.md:Tour", "exec"), namespace)  # noqa: S102
    capsys.readouterr()
    start, end = namespace["nll_start"], namespace["nll_end"]
    # training on the toy conditional sequences must pay off clearly (nats per frame)
    assert np.isfinite(end) and end < start - 2.0, (start, end)
    samples = np.asarray(namespace["samples"])
    mode = np.asarray(namespace["mode"])
    T, D = namespace["T"], namespace["D"]
    assert samples.shape == (2, T, D) and np.all(np.isfinite(samples))
    # the sampled mode follows the control: amplitude +-0.8 gives +-1.6 * sin(0.8 t + phase)
    t = np.arange(T)[:, None]
    wave = np.sin(0.8 * t + 0.7 * np.arange(D))
    np.testing.assert_allclose(mode[1], 1.6 * wave, atol=0.35)
    np.testing.assert_allclose(mode[0], -1.6 * wave, atol=0.35)
