"""Reward files are the user's code: what they do to their own interpreter stays in their own process.

Each hostile reward file is generated here and run by a real env (its worker a real process); outcomes are a
clean one-line RewardFunctionError naming the file, step and car, or a run that goes on unaffected. Hangs are
bounded by subprocess timeouts, never by timing assertions.
"""
import subprocess
import sys

import pytest

import multirace
from multirace.environment.rewards import RewardFunctionError

RETURNS_ONE = "    return 1.0\n"
HOSTILE = {
    "interrupts": ("def reward_function(params):\n    raise KeyboardInterrupt('from the function')\n",
                   "raised at step 1 for car_0: KeyboardInterrupt"),
    "alarm_off": ("import signal\ndef reward_function(params):\n    signal.signal(signal.SIGALRM, signal.SIG_IGN)\n"
                  "    signal.setitimer(signal.ITIMER_REAL, 0)\n    while True:\n        pass\n",
                  "did not return within 1 s at step 1 for car_0"),
    "hard_exit": ("import os\ndef reward_function(params):\n    os._exit(0)\n",
                  "ended its process (exit status 0) at step 1 for car_0"),
    "killed": ("import os, signal\ndef reward_function(params):\n    os.kill(os.getpid(), signal.SIGKILL)\n",
               "was killed by signal 9 at step 1 for car_0"),
    "isfinite_replaced": ("import math\nmath.isfinite = lambda value: True\n"
                          "def reward_function(params):\n    return float('nan')\n", "returned nan at step 1"),
    "closes_its_pipe": ("import os, sys\ndef reward_function(params):\n    os.close(int(sys.argv[2]))\n"
                        "    while True:\n        pass\n", "closed its pipe to the run (its process was ended)"),
    "lies_on_the_pipe": ("import os\ndef reward_function(params):\n    os.write(int(__import__('sys').argv[2]), "
                         "b'{\"garbage\\n')\n    return 1.0\n", "malformed reply"),
}


def _write(tmp_path, name: str, source: str):
    path = tmp_path / f"{name}.py"
    path.write_text(source)
    return path


@pytest.mark.parametrize("name", sorted(HOSTILE))
def test_a_hostile_reward_file_is_one_clear_error_naming_file_step_and_car(tmp_path, name):
    source, words = HOSTILE[name]
    env = multirace.parallel_env(num_cars=2, reward_function=_write(tmp_path, name, source), max_steps=5)
    env.reset(seed=0)
    with pytest.raises(RewardFunctionError) as err:
        env.step({"car_0": 7, "car_1": 7})
    message = str(err.value)
    assert f"{name}.py" in message and words in message and "\n" not in message, message
    env.close()


def test_a_reward_file_cannot_reach_the_env_through_the_call_stack(tmp_path):
    source = ("import sys\ndef reward_function(params):\n    frame = sys._getframe()\n    while frame:\n"
              "        for value in list(frame.f_locals.values()):\n"
              "            if hasattr(value, 'rules'):\n                value.rules.laps = 99\n"
              "        frame = frame.f_back\n" + RETURNS_ONE)
    env = multirace.parallel_env(num_cars=1, laps=1, reward_function=_write(tmp_path, "reach", source), max_steps=5)
    env.reset(seed=0)
    _, rewards, _, _, _ = env.step({"car_0": 7})
    assert rewards["car_0"] == 1.0 and env.rules.laps == 1
    env.close()


def test_copies_a_reward_function_forks_never_answer_for_it(tmp_path):
    source = "import os\ndef reward_function(params):\n    os.fork()\n    return params['steps'] / 10\n"
    env = multirace.parallel_env(num_cars=2, reward_function=_write(tmp_path, "forks", source), max_steps=20)
    env.reset(seed=0)
    for step in range(1, 11):
        _, rewards, _, _, _ = env.step({"car_0": 7, "car_1": 7})
        assert rewards == {"car_0": step / 10, "car_1": step / 10}
    env.close()


def test_the_run_ends_although_the_reward_function_started_a_thread_that_never_ends(tmp_path):
    path = _write(tmp_path, "thread", "import threading, time\ndef reward_function(params):\n"
                  "    threading.Thread(target=lambda: time.sleep(10**6)).start()\n" + RETURNS_ONE)
    code = ("import sys, multirace\nenv = multirace.parallel_env(num_cars=1, reward_function=sys.argv[1])\n"
            "env.reset(seed=0)\nfor _ in range(3):\n    env.step({'car_0': 7})\nprint('raced')\n")
    done = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and "raced" in done.stdout, done.stderr[-2000:]


def test_train_refuses_a_reward_file_that_ends_its_process_and_writes_no_agent(tmp_path):
    path = _write(tmp_path, "quits", "import os\ndef reward_function(params):\n    os._exit(0)\n")
    out = tmp_path / "agent.pt"
    done = subprocess.run([sys.executable, "-m", "multirace.cli", "train", "--config", "tiny", "--minutes", "0.05",
                           "--no-progress", "--envs", "1", "--cars", "1", "--reward", str(path), "--out", str(out)],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 2 and "quits.py ended its process (exit status 0)" in done.stderr, done.stderr[-2000:]
    assert "Traceback" not in done.stderr and not out.exists()


def test_a_reward_function_that_fails_late_in_training_is_one_message_not_a_traceback_per_worker(tmp_path):
    path = _write(tmp_path, "late", "def reward_function(params):\n    if params['steps'] > 20:\n"
                  "        raise ValueError('late failure')\n" + RETURNS_ONE)
    out = tmp_path / "agent.pt"
    done = subprocess.run([sys.executable, "-m", "multirace.cli", "train", "--config", "tiny", "--minutes", "30",
                           "--set", "max_iterations=2",  # step 21 comes in the first rollout (128 steps)
                           "--no-progress", "--envs", "2", "--cars", "2", "--reward", str(path), "--out", str(out)],
                          capture_output=True, text=True, timeout=900)
    assert done.returncode == 2, done.stderr[-3000:]
    assert done.stderr.count("late failure") == 1 and "Traceback" not in done.stderr, done.stderr[-3000:]
    assert "late.py raised at step 21" in done.stderr and not out.exists()


def test_a_forked_copy_of_the_run_neither_uses_nor_ends_the_runs_reward_process(tmp_path):
    path = _write(tmp_path, "steps", "def reward_function(params):\n    return params['steps'] / 10\n")
    code = ("import os, sys, multirace\nenv = multirace.parallel_env(num_cars=1, reward_function=sys.argv[1])\n"
            "env.reset(seed=0)\nenv.step({'car_0': 7})\npid = os.fork()\n"
            "if pid == 0:\n    assert env.step({'car_0': 7})[1]['car_0'] == 0.2\n    sys.exit(0)\n"
            "assert os.waitpid(pid, 0)[1] == 0\n"
            "assert env.step({'car_0': 7})[1]['car_0'] == 0.2\nprint('both stepped')\n")
    done = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and "both stepped" in done.stdout, done.stderr[-2000:]


def test_train_with_a_reward_function_that_forks_trains_once(tmp_path):
    path = _write(tmp_path, "forks_in_train", "import os\ndef reward_function(params):\n    os.fork()\n" + RETURNS_ONE)
    out = tmp_path / "agent.pt"
    done = subprocess.run([sys.executable, "-m", "multirace.cli", "train", "--config", "tiny", "--minutes", "0.05",
                           "--no-progress", "--envs", "1", "--cars", "1", "--reward", str(path), "--out", str(out)],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0 and done.stdout.count(f"wrote {out}") == 1, done.stdout[-2000:] + done.stderr[-2000:]
    assert out.exists()
