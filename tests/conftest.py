"""Test configuration.

- x64 on, as physics users run JAX. Scenes and `jc.build` then default to float64 (JAX's default float dtype);
  float32 paths are exercised through explicit `dtype=np.float32`. tests/test_precision.py also runs the main
  calls under strict dtype promotion, and a subprocess with x64 off.
- Most of the suite's time is XLA compiling small programs that then run for milliseconds. Two settings cut it;
  neither changes what is computed beyond rounding, and speed is measured by `python -m jaxcon bench`, never
  here. Both are exported through the environment, so the notebook kernels and subprocesses the suite starts
  use them too, and a value already set in the environment is kept.
  - XLA at its lowest optimisation effort (JAX_DISABLE_MOST_OPTIMIZATIONS=1). Tests that run one program for
    many iterations (the long fits) carry `@pytest.mark.optimised` and compile at the default effort. Set
    JAX_DISABLE_MOST_OPTIMIZATIONS=0 to run everything fully optimised.
  - One persistent compilation cache for the run (JAX_COMPILATION_CACHE_DIR, a temporary folder removed at the
    end), shared by the pytest-xdist workers, notebook kernels and subprocesses, so a program that several of
    them build is compiled once.
- Each compiled XLA CPU executable holds about six memory maps, and JAX's jit caches keep every executable that
  a long-lived function (`jc.rollout`, the solvers) compiled, one per model size and setting. A pytest worker
  that runs 300 tests reaches Linux's default limit of 65,530 maps (vm.max_map_count), after which the next
  compile aborts or segfaults inside XLA (seen in full runs on 2026-11-24, in `backend_compile_and_load` and in
  the persistent cache's `put_executable_and_time`). After each test, a worker above `_MAX_MAPS` maps clears
  JAX's caches (`_bound_live_executables`); later tests recompile what they need, or read it from the
  persistent cache.
"""
import gc
import os
import shutil
import tempfile

import pytest

os.environ.setdefault("JAX_DISABLE_MOST_OPTIMIZATIONS", "1")
if "xla_cpu_use_fusion_emitters" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_use_fusion_emitters=false").strip()
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:     # the controller makes it; the xdist workers inherit it
    os.environ["JAX_COMPILATION_CACHE_DIR"] = tempfile.mkdtemp(prefix="jaxcon-test-xla-cache-")
    os.environ["JAXCON_TEST_CACHE_OWNED"] = str(os.getpid())
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "0")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
SUITE_DISABLES_OPTIMIZATIONS = os.environ["JAX_DISABLE_MOST_OPTIMIZATIONS"].lower() in ("1", "true", "t", "yes",
                                                                                       "y", "on")
jax.config.update("jax_disable_most_optimizations", SUITE_DISABLES_OPTIMIZATIONS)
jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])
jax.config.update("jax_persistent_cache_min_compile_time_secs",
                  float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"]))
jax.config.update("jax_persistent_cache_min_entry_size_bytes",
                  int(os.environ["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"]))


@pytest.fixture(autouse=True)
def _optimised(request):
    """`@pytest.mark.optimised`: this test's programs compile at XLA's default effort (module docstring)."""
    if request.node.get_closest_marker("optimised") is None:
        yield
        return
    jax.config.update("jax_disable_most_optimizations", False)
    try:
        yield
    finally:
        jax.config.update("jax_disable_most_optimizations", SUITE_DISABLES_OPTIMIZATIONS)


def pytest_unconfigure(config):
    if os.environ.get("JAXCON_TEST_CACHE_OWNED") == str(os.getpid()):
        shutil.rmtree(os.environ["JAX_COMPILATION_CACHE_DIR"], ignore_errors=True)


_MAX_MAPS = 36_000      # under vm.max_map_count = 65,530 by ten times the most one test added (2,942, 2026-11-24)


def _map_count():
    try:
        with open("/proc/self/maps", "rb") as f:
            return sum(1 for _ in f)
    except OSError:
        return None       # not Linux: no /proc/self/maps to count, nothing done


@pytest.fixture(autouse=True)
def _bound_live_executables():
    """Keeps this worker's compiled executables (and their memory maps) bounded (module docstring)."""
    yield
    n = _map_count()
    if n is not None and n > _MAX_MAPS:
        jax.clear_caches()
        gc.collect()


# The extended set (`python -m pytest -m slow`): variants whose property the default suite also checks, on a
# sibling case or in another test, kept out of the default run to hold it under 15 minutes on 2 cores. Each was
# in the default suite and passed in the full run of 2026-11-24 (692 passed) before moving here.
SLOW = {
    # the float32 friction-gradient NaN's reproducer: its cause is test_restitution_scale_reverse_mode_is_finite_
    # when_the_phases_agree, and the falling chain's float32 friction gradient against differences is
    # test_contact_leaf_gradients_reverse_equals_forward_and_differences[falling_chain]
    "tests/test_contacts_gradients.py::test_falling_chain_friction_gradient_in_float32",
    # billiards' gradient against differences: test_contacts.py::test_billiards_shot_gradient_matches_...; every
    # contact leaf's gradient: the falling-chain case of the same test (the drape's is in this set too)
    "tests/test_contacts_gradients.py::test_contact_leaf_gradients_reverse_equals_forward_and_differences[billiards]",
    # SoftStep's contact gradients are finite: its drape hard case and test_contacts_solvers' gradient tests
    "tests/test_contacts_gradients.py::test_other_solvers_contact_leaf_gradients_are_finite_in_float32"
    "[SoftStep-drape]",
    # the speed-vs-error bench's files and table; notebook 02 runs its scenes
    "tests/test_speed_vs_error.py::test_speed_vs_error_small",
    # the fit's defaults: test_fit.py::test_defaults_fit_a_chain_released_from_a_violated_start
    "tests/test_fit.py::test_defaults_fit_cloth_rest_lengths_from_nominal",
    # batched_rollout equals vmap: PGS (Baumgarte) and every other solver stay; split impulses under vmap:
    # test_split_impulses.py::test_split_works_in_float32_and_under_vmap
    "tests/test_batching.py::test_batched_rollout_equals_vmap_of_rollout[PGSsplit]",
    # a set's parameter and compliance gradients: plain PGS and every other solver stay
    "tests/test_constraints.py::test_gradients_wrt_a_constraints_params_and_compliance[PGS-implicit]",
    "tests/test_constraints.py::test_gradients_wrt_a_constraints_params_and_compliance[PGS-split]",
    # the bench's plain scatter-add reference: a bench concern (test_batching checks the batch-minor reference)
    "tests/test_solvers_a.py::test_plain_scatter_add_reference_is_the_same_pgs",
    # the landing pile on the grid with substeps: every solver's grid path (one search per step, its substeps,
    # its rows) stays in test_contacts_grid_solvers.py::test_grid_pair_friction_holds_and_slides_as_scipy, and a
    # landing pile on the grid in test_contacts_grid.py::test_pile_settles_without_overlap[grid]
    "tests/test_contacts_grid_solvers.py::test_a_pile_lands_and_rests_on_the_grid_with_every_solver[PGS]",
    "tests/test_contacts_grid_solvers.py::test_a_pile_lands_and_rests_on_the_grid_with_every_solver[Jacobi]",
    "tests/test_contacts_grid_solvers.py::test_a_pile_lands_and_rests_on_the_grid_with_every_solver[SoftStep]",
    "tests/test_contacts_grid_solvers.py::test_a_pile_lands_and_rests_on_the_grid_with_every_solver[XPBD]",
    "tests/test_contacts_grid_solvers.py::test_a_pile_lands_and_rests_on_the_grid_with_every_solver[Penalty]",
    "tests/test_contacts_grid_solvers.py::test_penalty_on_the_grid_equals_all_pairs_in_3d",
    # batched_rollout of a contact model is a vmap of rollout: test_contacts.py::test_step_and_batched_rollout_...
    "tests/test_contacts_grid_solvers.py::test_batched_rollout_of_a_grid_model_equals_one_rollout_per_state",
    # a 3-D grid: test_contacts_grid.py::test_an_impact_cannot_send_a_disc_through_one_that_was_no_candidate[3]
    "tests/test_contacts_grid_solvers.py::test_a_3d_pile_rests_on_the_grid_with_substeps",
    # jc.fit through a grid: its gradient is test_contacts_grid.py::test_grid_gradients_equal_central_differences
    "tests/test_contacts_grid_solvers.py::test_fit_recovers_the_restitution_of_grid_pairs",
    # XPBD's grid gradient on discs: PGS's stays (test_grid_gradients_equal_central_differences[PGS]: the same
    # grid step and search), and XPBD's grid rows are exercised by test_contacts_grid_solvers.py's friction test
    "tests/test_contacts_grid.py::test_grid_gradients_equal_central_differences[XPBD]",
    # the drape's contact-leaf gradients against differences: the falling chain's stay in the same test, and the
    # drape's (sphere and plane) gradients are finite in test_other_solvers_contact_leaf_gradients_..[XPBD-drape]
    "tests/test_contacts_gradients.py::test_contact_leaf_gradients_reverse_equals_forward_and_differences[drape]",
    # the 24x24 cloth's self-collision (issue 25's acceptance size, measured in docs/contacts.md): the 10x10 cloth
    # on the grid stays (PGS) in the same test; PGS's self-collision gradient: XPBD's stays (the
    # same grid step, search and pairs)
    "tests/test_contacts_self.py::test_a_cloth_dropped_and_folded_on_the_floor_never_passes_through_itself[PGS-24]",
    "tests/test_contacts_self.py::test_a_cloth_dropped_and_folded_on_the_floor_never_passes_through_itself[XPBD-24]",
    "tests/test_contacts_self.py::test_self_collision_gradients_equal_central_differences[PGS]",
    # XPBD's 10x10 fold: PGS's stays in the same test, and XPBD's self-collision rows on the grid are in the
    # gradient test test_self_collision_gradients_equal_central_differences[XPBD]
    "tests/test_contacts_self.py::test_a_cloth_dropped_and_folded_on_the_floor_never_passes_through_itself[XPBD-10]",
    # XPBD's self-collision gradient: the grid's search, path check and slots under reverse mode stay in
    # test_contacts_grid.py::test_grid_gradients_equal_central_differences[PGS]
    "tests/test_contacts_self.py::test_self_collision_gradients_equal_central_differences[XPBD]",
    # PGS's 10x10 fold: self-collision on the grid stays in test_a_chain_that_coils_on_the_floor_never_passes_
    # through_itself_2d_float32, and the check's failure without it in test_the_same_cloth_without_self_collision_..
    "tests/test_contacts_self.py::test_a_cloth_dropped_and_folded_on_the_floor_never_passes_through_itself[PGS-10]",
    # the all-pairs baseline of the grid's landing pile: all-pairs piles are tests/test_contacts_piles.py's
    "tests/test_contacts_grid.py::test_pile_settles_without_overlap[True]",
    # Jacobi's energy on the grid: PGS's stays; Jacobi's grid rows: the pair-friction test against SciPy
    "tests/test_contacts_grid.py::test_energy_never_increases_without_gravity[solver1]",
    # the compact table against the unrolled layout with ropes mixed into its colours, for six solvers: PGS's
    # gradient through both (test_compact_layout_gradient_matches_unrolled_and_differences, which runs the same
    # mixed cloth) and every solver's layouts (test_strided_gather_and_compact_layouts_agree) stay
    "tests/test_core.py::test_compact_layout_with_mixed_ropes_agrees",
    # a set's box colours against the rods for Jacobi and SoftStep: PGS's and XPBD's stay (the same box reads and
    # pad writes, through rows.rel / rows.apply and XPBD's position rows)
    "tests/test_constraints_layout.py::test_a_cloth_of_user_distances_on_boxes_equals_the_rods[Jacobi]",
    "tests/test_constraints_layout.py::test_a_cloth_of_user_distances_on_boxes_equals_the_rods[SoftStep]",
    # a set's parameter gradients for SoftStep and RATTLE: PGS, Jacobi, Direct, XPBD, Penalty and PGS-split stay
    # in the same test, and SoftStep's and RATTLE's rod gradients against differences in
    # tests/test_gradients_all_solvers.py
    "tests/test_constraints.py::test_gradients_wrt_a_constraints_params_and_compliance[SoftStep]",
    "tests/test_constraints.py::test_gradients_wrt_a_constraints_params_and_compliance[RATTLE]",
    # RATTLE's gradient through a hub star: PGS's and XPBD's stay (the same star block and its solve)
    "tests/test_hubs.py::test_gradient_through_a_star_matches_central_differences[RATTLE]",
    # finite gradients through start overlaps at coincident centres: the rods' coincident-particle gradients
    # (test_core.py::test_coincident_particles_give_finite_values_and_gradients) and the start overlaps'
    # push-out (the other tests of tests/test_contacts_start_overlaps.py) stay
    "tests/test_contacts_start_overlaps.py::test_start_overlap_gradients_are_finite",
    # reverse mode through a set's gather colours: reverse mode through its box colours stays for every solver
    # (test_constraints.py::test_gradients_wrt_a_constraints_params_and_compliance: the arm's two angle rows are
    # two colours of their own), and the gather colours' forward pass in test_an_irregular_graph_of_user_
    # distances_is_gathered_and_equals_the_rods
    "tests/test_constraints_layout.py::test_the_gradient_through_gathered_colours_equals_the_scanned_tables",
    # Jacobi's convergence to PGS's velocities on the break's impact step: Jacobi's break stays
    # (test_billiards_break_conserves_momentum_and_never_gains_energy[Jacobi], test_hard_contact_case[Jacobi-..])
    "tests/test_contacts_solvers_b.py::test_jacobi_relaxations_converge_on_a_tight_rack",
    # a contact that never touches changes no constraint row: the PGS and Jacobi variants stay (velocity level
    # Gauss-Seidel and Jacobi), and every solver's model without contacts traces no contact code
    # (test_contacts_solvers.py::test_models_without_contacts_trace_no_contact_code)
    "tests/test_contacts_solvers.py::test_a_contact_that_never_touches_changes_no_constraint_row[SoftStep]",
    "tests/test_contacts_solvers.py::test_a_contact_that_never_touches_changes_no_constraint_row[Penalty]",
    "tests/test_contacts_solvers.py::test_a_contact_that_never_touches_changes_no_constraint_row[XPBD]",
    # Penalty's gradient through a glancing collision: XPBD's stays, and Penalty's contact gradients against
    # differences stay in test_sliding_to_rest_distance_and_gradients[Penalty]
    "tests/test_contacts_solvers.py::test_glancing_collision_gradient_matches_differences[Penalty]",
    # hard contact cases with a sibling: SoftStep's break stays in test_contacts_solvers_b.py::test_billiards_break_
    # conserves_momentum_and_never_gains_energy[SoftStep]; the split PGS drape in [PGS-drape_from_1m] and
    # [PGS-split-break_16_dt_1_60]; Penalty's drape in its break and heavy-on-light cases and the other solvers'
    # drapes
    "tests/test_hard_cases_contacts.py::test_hard_contact_case[SoftStep-break_16_dt_1_60]",
    "tests/test_hard_cases_contacts.py::test_hard_contact_case[PGS-split-drape_from_1m]",
    "tests/test_hard_cases_contacts.py::test_hard_contact_case[Penalty-drape_from_1m]",
}


@pytest.hookimpl(tryfirst=True)          # before `-m` deselects by marker
def pytest_collection_modifyitems(config, items):
    found = {item.nodeid for item in items}
    files = {n.split("::")[0] for n in found}
    missing = sorted(n for n in SLOW if n.split("::")[0] in files and n not in found)
    assert not missing, f"tests/conftest.py SLOW names tests that do not exist: {missing}"
    for item in items:
        if item.nodeid in SLOW:
            item.add_marker(pytest.mark.slow)
