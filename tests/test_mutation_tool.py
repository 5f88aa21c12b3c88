"""tools/mutation.py: how it counts mutants, picks tests and sets the JIT mode."""

import os

import jax

from tests import seqdata


def test_mutation_script_counts_mutants_and_sets_the_jit_mode(tmp_path, monkeypatch):
    """tools/mutation.py: an equivalent mutant and an unchecked one are not in the
    rate, a timeout is not a kill (except a listed mutant that breaks the import); the
    hook it appends to the scratch conftest runs only mutmut's call-recording run op by
    op; results of separate runs merge."""
    mu = seqdata.load_script("mutation", "tools")
    equivalent = next(iter(mu.EQUIVALENT))
    status = {"m.x_a__mutmut_1": "killed", "m.x_a__mutmut_2": "survived",
              "m.x_a__mutmut_3": "timeout", "m.x_a__mutmut_4": "not checked",
              equivalent: "survived"}
    counts, tested, killed = mu.summarize(status)
    assert (tested, killed) == (3, 1) and equivalent not in counts
    # the results list a timed-out mutant with the survivors, marked as such
    assert mu.row("m.py", status, None)[-1] == ["m.x_a__mutmut_2",
                                                "m.x_a__mutmut_3 (timed out)"]
    # a mutant that breaks the module's import exits before any test (mutmut: timeout):
    # a kill only when it is listed in BREAKS_IMPORT, and only for that exit
    breaks = next(iter(mu.BREAKS_IMPORT))
    _, _, run, killed, *_ = mu.row("m.py", {**status, breaks: "timeout"}, None)
    assert (run, killed) == (4, 2)
    _, _, run, killed, *_, survivors = mu.row("m.py", {**status, breaks: "survived"}, None)
    assert (run, killed) == (4, 1) and breaks in survivors
    # the rate is rounded down: one survivor among 203 is not 100%
    many = {f"m.x_a__mutmut_{i}": "killed" for i in range(202)}
    assert mu.row("m.py", {**many, "m.x_b__mutmut_1": "survived"}, None)[4] == "99.5%"
    assert mu.row("m.py", many, None)[4] == "100%"
    assert mu.row("m.py", status, None)[4] == "33.3%"
    conftest = open(os.path.join(os.path.dirname(__file__), "conftest.py")).read()
    assert "\nimport jax\n" in conftest and "\nimport os\n" in conftest  # the hook's names
    ns = {"jax": jax, "os": os}
    exec(mu.STATS_OP_BY_OP, ns)
    try:
        monkeypatch.setenv("MUTANT_UNDER_TEST", "stats")
        ns["pytest_sessionstart"](None)
        assert jax.config.jax_disable_jit
        monkeypatch.setenv("MUTANT_UNDER_TEST", "jtus.losses.x_make__mutmut_1")
        ns["pytest_sessionstart"](None)
        assert not jax.config.jax_disable_jit
    finally:
        jax.config.update("jax_disable_jit", False)
    import tomllib
    for module, k in (("jtus/models/kpn.py", True), ("jtus/losses.py", False)):
        cfg = tomllib.loads(mu.config_block(module, mu.TESTS[module]))["tool"]["mutmut"]
        assert cfg["paths_to_mutate"] == [module] and cfg["tests_dir"] == mu.TESTS[module]
        args = cfg["pytest_add_cli_args"]
        assert args[:2] == ["-n", "0"] and ("-k" in args) == k
        if k:
            assert args[args.index("-k") + 1].startswith("not test_trains_with_decreasing")
    # a model's scope: its step's functions and its Config's methods, not its FLOP count
    globs, sep = mu.scope_globs("jtus/models/tus.py"), "\u01c1"  # mutmut's class separator
    assert "jtus.models.tus.x_step__mutmut_*" in globs
    assert f"jtus.models.tus.x{sep}Config{sep}*" in globs
    assert not any("x_cost_" in g for g in globs) and mu.scope_globs("jtus/losses.py") == []
    assert not mu.in_scope("jtus/models/tus.py", "jtus.models.tus.x_cost__mutmut_2")
    assert mu.in_scope("jtus/models/tus.py", "jtus.models.tus.x__beta__mutmut_2")
    method = f"jtus.models.tus.x{sep}Config{sep}__post_init____mutmut_1"
    assert mu.in_scope("jtus/models/tus.py", method)
    assert mu.in_scope("jtus/losses.py", "jtus.losses.x_cost__mutmut_1")
    out = str(tmp_path / "results.md")
    mu.write_results(out, [("jtus/metrics.py", 10, 9, 9, "100%", 5.0, [])], "cmd-a")
    mu.write_results(out, [("jtus/losses.py", 20, 18, 17, "94%", 7.0, ["m.x_b"])], "cmd-b")
    text = open(out).read()
    assert "| `jtus/metrics.py` | 10 | 9 | 9 | 100% |" in text and "`cmd-a`" in text
    assert "| `jtus/losses.py` | 20 | 18 | 17 | 94% |" in text and "`m.x_b`" in text
    mu.write_results(out, [("jtus/rollout.py", 9, 4, 4, "100%", None, [])], "cmd-c")
    text = open(out).read()  # a --save-only row has no seconds; the others are kept
    assert "| `jtus/rollout.py` | 9 | 4 | 4 | 100% | - | `cmd-c`" in text and "`cmd-a`" in text
