"""The command line starts light: building the parser imports no heavy library.

(How fast `multirace --help` starts is measured by `multirace bench`, not asserted here.)
"""
import subprocess
import sys

HEAVY = ("torch", "numba", "pybullet", "rerun", "cv2", "matplotlib", "ray", "pettingzoo")


def test_parser_and_every_subcommand_help_import_no_heavy_library():
    code = ("import sys, contextlib, io\n"
            "from multirace.cli import build_parser\n"
            "parser = build_parser()\n"
            "names = [a for a in parser._subparsers._group_actions[0].choices]\n"
            "for name in names:\n"
            "    with contextlib.redirect_stdout(io.StringIO()):\n"
            "        try:\n"
            "            parser.parse_args([name, '--help'])\n"
            "        except SystemExit:\n"
            "            pass\n"
            f"print(sorted(m for m in {HEAVY!r} if m in sys.modules), len(names))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out[0] == "[]", f"building the CLI parser imported {out}"
    assert int(out[-1]) >= 10  # race, agent, imitate, replay, explain, plot, bench, train, evaluate, league


def test_shipped_agents_race_by_name(tmp_path, monkeypatch):
    from multirace.cli import main

    monkeypatch.chdir(tmp_path)  # away from the checkout's agents/ folder
    out = tmp_path / "r.json"
    assert main(["race", "dagger_small", "bot:follow@1.5", "--laps", "1", "--json", str(out)]) == 0
    import json

    import hashlib

    from multirace.resources import agents_dir

    cars = {c["name"]: c for c in json.loads(out.read_text())["cars"]}
    shipped = hashlib.sha256((agents_dir() / "dagger_small.pt").read_bytes()).hexdigest()
    assert cars["dagger_small"]["file_sha256"] == shipped and cars["dagger_small"]["status"] != "forfeit"
