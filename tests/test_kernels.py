"""The first env on a machine compiles numba kernels for 10-30 s: it says so once, and only then."""
import importlib.util
import sys

import multirace
from multirace.environment import kernels


def test_the_compile_notice_is_printed_once_and_only_while_a_kernel_is_uncached(tmp_path, monkeypatch, capsys):
    env = multirace.parallel_env(num_cars=1)
    env.reset(seed=0)
    env.step({car: env.action_space(car).sample() for car in env.agents})
    env.close()
    assert kernels.uncached_kernels() == []  # every kernel the env used is in numba's cache now
    source = tmp_path / "probe.py"  # a kernel never compiled: numba has no cache index for it
    source.write_text("import numba\n\n@numba.njit(cache=True)\ndef probe(x):\n    return x + 1\n")
    spec = importlib.util.spec_from_file_location("multirace._probe", source)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    monkeypatch.setitem(sys.modules, "multirace._probe", module)
    assert kernels.uncached_kernels() == ["multirace._probe.probe"]
    monkeypatch.setattr(kernels, "_checked", False)
    assert kernels.announce_compile() is True
    assert kernels.announce_compile() is False  # once per process
    assert capsys.readouterr().err.count("compiling the physics and renderer kernels") == 1


def test_a_race_without_a_lidar_does_not_load_the_lidar_kernels():
    """Kernels of a module a race loads but never calls are never cached, so they would bring the notice back on
    every run: a camera race does not load the LIDAR's beam kernels."""
    import subprocess

    code = ("import sys, multirace\nenv = multirace.parallel_env(num_cars=1)\nenv.reset(seed=0)\n"
            "env.step({car: env.action_space(car).sample() for car in env.agents})\n"
            "print('multirace.sensors.beams' in sys.modules)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "False"
