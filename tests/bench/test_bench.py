import json

from ntp_engine.bench import dump_json, print_table, timed


def test_helpers(tmp_path, capsys):
    calls = []
    assert timed(lambda: calls.append(1), repeat=2) >= 0 and len(calls) == 3  # one warm-up
    print_table([("a", 1), ("bbb", 22)], ("name", "n"))
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("name") and set(lines[1]) <= {"-", " "} and len(lines) == 4
    dump_json(tmp_path / "r.json", {"x": 1})
    assert json.loads((tmp_path / "r.json").read_text()) == {"x": 1}
