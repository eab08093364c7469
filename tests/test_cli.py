"""The console command restarts itself with tcmalloc preloaded, once, where it can."""

from __future__ import annotations

import subprocess
import sys

from gridnerf import cli

LIB = cli.TCMALLOC_PATHS[0]


def _calls(environ, present=(LIB,)):
    calls = []
    restarted = cli.preload_tcmalloc(environ, exists=lambda p: p in present,
                                     execve=lambda exe, args, env: calls.append((exe, args, env)))
    return restarted, calls


def test_restarts_with_tcmalloc_first_in_ld_preload():
    restarted, calls = _calls({"PATH": "/bin", "LD_PRELOAD": "/opt/libother.so"})
    assert restarted and len(calls) == 1
    exe, args, env = calls[0]
    assert exe == sys.executable and args[0] == sys.executable
    assert env["LD_PRELOAD"] == f"{LIB} /opt/libother.so" and env["PATH"] == "/bin"


def test_no_restart_when_preloaded_opted_out_or_missing():
    for environ, present in (({"LD_PRELOAD": LIB}, (LIB,)),
                             ({cli.MALLOC_ENV: "system"}, (LIB,)),
                             ({}, ())):
        assert _calls(environ, present) == (False, [])


def test_a_failed_restart_goes_on_without_it():
    def fail(exe, args, env):
        raise OSError("exec format error")

    assert not cli.preload_tcmalloc({}, exists=lambda p: True, execve=fail)


def test_main_with_argv_never_restarts(monkeypatch, capsys):
    monkeypatch.setattr(cli, "preload_tcmalloc", lambda: (_ for _ in ()).throw(AssertionError))
    assert cli.main(["simulate", "no_such_scene"]) == 2
    assert "unknown scene" in capsys.readouterr().err


def test_the_console_command_runs_once_restarted():
    # the restarted process must parse the same arguments: an unknown scene is one error
    # line and exit 2 whether or not this machine has tcmalloc
    out = subprocess.run([sys.executable, "-m", "gridnerf.cli", "simulate", "no_such_scene"],
                         capture_output=True, text=True, env={"PATH": "/usr/bin:/bin"})
    assert out.returncode == 2
    assert out.stderr.count("\n") == 1 and "unknown scene" in out.stderr
