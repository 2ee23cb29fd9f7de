"""Suite-wide settings: dtype from JAX_ENABLE_X64, strict rank promotion, hypothesis profile."""

import jax
import pytest
from hypothesis import HealthCheck, settings

# Accidental implicit broadcasting is a bug in library code: make it an error.
jax.config.update("jax_numpy_rank_promotion", "raise")

settings.register_profile(
    "jaxquat",
    max_examples=25,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
    derandomize=True,
)
settings.load_profile("jaxquat")


def pytest_report_header(config):
    return f"jaxquat suite: jax {jax.__version__}, x64={jax.config.jax_enable_x64}"


@pytest.fixture
def x64():
    return bool(jax.config.jax_enable_x64)
