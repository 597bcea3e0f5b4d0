import pytest


@pytest.fixture(scope="session", autouse=True)
def _agent_kernels_built():
    """The agents' ahead-of-time kernels (`bridge.swarm.aot`) built once before the first test
    here, so that no test's agent spends its connect timeout building them (a fresh clone has
    none). Where they cannot be built the agents run on the JIT, as a user's would."""
    from bridge.swarm import aot

    try:
        aot.ensure()
    except aot.AotError:
        pass
    yield
