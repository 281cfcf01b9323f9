"""The persistent compilation cache: where it lives, how it is turned off, that a second
process reads what the first compiled, and that the test session shares one folder."""

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import pytest

from gara_jax import cli, compile_cache

ROOT = Path(__file__).resolve().parent.parent

# A fresh process that turns the cache on in FOLDER, compiles one small program and prints
# how many programs it read from the cache.
_PROBE = """
import sys, json
from gara_jax import compile_cache
from jax import monitoring
hits = []
monitoring.register_event_listener(
    lambda event, **_: hits.append(1) if event == "/jax/compilation_cache/cache_hits" else None)
compile_cache.enable(sys.argv[1], min_compile_time_s=0.0)
import jax, jax.numpy as jnp
out = jax.jit(lambda x: jnp.cumsum(jnp.sin(x) * 3.0) @ x)(jnp.arange(64.0))
print(json.dumps({"hits": len(hits), "value": float(out)}))
"""


@pytest.mark.parametrize("value", ["0", "off", "False", "no"])
def test_off_values_turn_it_off(monkeypatch, value):
    monkeypatch.setenv(compile_cache.ENV_VAR, value)
    assert compile_cache.resolve() is None
    assert compile_cache.enable() is None


def test_folder_default_and_xdg(monkeypatch, tmp_path):
    monkeypatch.setenv(compile_cache.ENV_VAR, str(tmp_path / "here"))
    assert compile_cache.resolve() == tmp_path / "here"
    assert compile_cache.resolve(disable=True) is None
    monkeypatch.delenv(compile_cache.ENV_VAR)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert compile_cache.resolve() == tmp_path / "xdg" / "gara-jax" / "jax"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert compile_cache.resolve() == tmp_path / "home" / ".cache" / "gara-jax" / "jax"
    monkeypatch.setenv(compile_cache.ENV_VAR, "on")
    assert compile_cache.resolve() == tmp_path / "home" / ".cache" / "gara-jax" / "jax"


def test_a_file_instead_of_a_folder_is_refused_by_name(monkeypatch, tmp_path):
    (tmp_path / "f").write_text("x")
    monkeypatch.setenv(compile_cache.ENV_VAR, str(tmp_path / "f"))
    with pytest.raises(ValueError, match="GARA_JAX_COMPILE_CACHE=.* is a file"):
        compile_cache.resolve()


def test_every_command_takes_no_compile_cache():
    parser = cli.build_parser()
    for name in cli.COMMANDS:
        assert parser.parse_args([name, "--no-compile-cache"]).no_compile_cache is True
        assert parser.parse_args([name]).no_compile_cache is False


def test_a_second_process_reads_the_program_the_first_compiled(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != compile_cache.ENV_VAR}
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH")) if p)
    runs = [json.loads(subprocess.run(
        [sys.executable, "-c", _PROBE, str(tmp_path / "cache")], capture_output=True,
        text=True, check=True, cwd=ROOT, env=env).stdout.splitlines()[-1]) for _ in range(2)]
    assert runs[0]["hits"] == 0 and runs[1]["hits"] >= 1
    assert runs[0]["value"] == runs[1]["value"]  # the cached program computes the same
    assert any((tmp_path / "cache").iterdir())


def test_the_test_session_shares_one_folder():
    # tests/conftest.py: the controller chose the folder, the workers inherited it (or the
    # run was started with GARA_JAX_COMPILE_CACHE=0 and nobody turned it on).
    folder = compile_cache.resolve()
    if folder is None:
        assert jax.config.values["jax_compilation_cache_dir"] is None
    else:
        assert folder.is_dir()
        assert jax.config.values["jax_compilation_cache_dir"] == str(folder)
