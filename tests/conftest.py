"""Test configuration: x64 on, as physics users run JAX. Scenes and `jc.build` then default to float64 (JAX's
default float dtype); float32 paths are exercised through explicit `dtype=np.float32`. tests/test_precision.py
also runs the main calls under strict dtype promotion, and a subprocess with x64 off."""
import jax

jax.config.update("jax_enable_x64", True)


# The slowest tests (each 20 s or more on a 2-core CPU, measured with --durations), started first: with
# pytest-xdist a long test that starts last keeps one worker busy while the other idles. Half of them go to the
# front of each worker's share of the collection (`--dist worksteal` splits it in two contiguous halves).
SLOW_FIRST = (
    "test_speed_vs_error.py::test_speed_vs_error_small",
    "test_api_contract.py::test_bench_writes_json",
    "test_notebooks.py::test_notebook_runs_in_a_kernel[04_contacts]",
    "test_batching.py::test_batched_rollout_equals_vmap_of_rollout[RATTLE]",
    "test_batching.py::test_gradient_through_batched_rollout_is_exact",
    "test_contacts.py::test_billiards_shot_gradient_matches_differences_even_head_on",
    "test_notebooks.py::test_notebook_runs_in_a_kernel[03_system_identification]",
    "test_fit.py::test_defaults_fit_cloth_rest_lengths_from_nominal",
    "test_precision.py::test_scene_values_trace_under_jit_grad_and_vmap[cloth]",
    "test_gradgrowth.py::test_matches_jax_grad_of_rollout",
    "test_solvers_a.py::test_plain_scatter_add_reference_is_the_same_pgs",
    "test_batching.py::test_batched_rollout_shards_the_batch_over_every_device",
    "test_api_contract.py::test_demo_runs",
    "test_contacts_grid.py::test_gradient_through_a_grid_rollout_is_finite",
)


def pytest_collection_modifyitems(config, items):
    rank = {name: k for k, name in enumerate(SLOW_FIRST)}
    key = lambda item: rank.get(item.nodeid.split("/")[-1])       # noqa: E731
    slow = sorted((it for it in items if key(it) is not None), key=key)
    rest = [it for it in items if key(it) is None]
    half = len(rest) // 2
    items[:] = slow[0::2] + rest[:half] + slow[1::2] + rest[half:]
