"""A fleet's inputs: a directory, a glob, @LIST, s3:// (moto's server on 127.0.0.1) and an http
directory listing give the same rows as the same local files (issue 40, item 1)."""
from __future__ import annotations

import sys

import pytest

from mavcal.cli import main
from mavcal.errors import SourceError, UsageError
from mavcal.fleet.inputs import expand_sources, is_url
from mavcal.fleet.run import run_fleet
from mavcal.fleet.table import read_table
from mavcal.pipeline import Options
from mavcal.testing.fleet import assert_same_rows, comparable, make_fleet, moto_s3

FAST = Options(uncertainty_draws=50)


@pytest.fixture(scope="module")
def fleet(tmp_path_factory, sitl_dir, real_dir):
    root = tmp_path_factory.mktemp("fleet")
    logs = make_fleet(root, sitl_dir, real_dir)
    table = root.parent / "local.csv"
    run_fleet([str(p) for p in logs], FAST, jobs=2, table=str(table))
    return root, logs, read_table(table)


def test_directory_glob_and_list_expand_to_the_logs(fleet, tmp_path):
    root, logs, _ = fleet
    want = [str(p) for p in logs]
    assert expand_sources([str(root)]) == want  # recursive, by extension; notes.txt left out
    assert sorted(expand_sources([f"{root}/**/*.tlog"])) == [p for p in want if p.endswith(".tlog")]
    lst = tmp_path / "paths.txt"
    rel = [str(p.relative_to(root)) for p in logs]
    lst.write_text("# the fleet\n\n" + "\n".join(rel[:2]) + f"\n{root}/b\n{rel[0]}\n")
    (tmp_path / rel[0]).parent.mkdir(parents=True, exist_ok=True)
    for p, r in zip(logs, rel):  # relative lines are relative to the list file
        (tmp_path / r).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / r).write_bytes(p.read_bytes())
    got = expand_sources([f"@{lst}"])
    assert got[:2] == [str(tmp_path / r) for r in rel[:2]]
    assert got[2:] == [p for p in want if p.startswith(f"{root}/b/")]  # the duplicate line dropped


def test_bad_inputs_say_so_in_one_line(tmp_path):
    with pytest.raises(SourceError, match="no log file"):
        expand_sources([str(tmp_path)])
    with pytest.raises(SourceError, match="no file matches"):
        expand_sources([f"{tmp_path}/*.tlog"])
    with pytest.raises(SourceError, match="cannot read the list file"):
        expand_sources([f"@{tmp_path}/missing.txt"])
    assert is_url("s3://b/k") and is_url("https://h/x.tlog") and not is_url("udpin:0.0.0.0:14550")


def test_url_without_the_fleet_extra_names_it(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "fsspec", None)  # as if not installed
    with pytest.raises(UsageError, match=r"mavcal\[fleet\]"):
        expand_sources(["s3://bucket/logs/"])
    assert main(["calibrate", "s3://bucket/logs/"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pip install 'mavcal[fleet]'" in err[0]


def test_list_file_gives_the_local_rows(fleet, tmp_path):
    """(The directory's expansion is the fixture's list of logs: test_directory_glob_and_list_expand_to_the_logs.)"""
    root, logs, local = fleet
    lst = tmp_path / "paths.txt"
    lst.write_text("\n".join(str(p) for p in logs) + "\n")
    table = tmp_path / "list.csv"
    run_fleet(expand_sources([f"@{lst}"]), FAST, jobs=1, table=str(table))
    want = comparable(local, str(root))
    assert len(want) == len(logs) and len({r[0] for r in want}) == len(logs)
    assert_same_rows(comparable(read_table(table), str(root)), want)


def test_s3_prefix_gives_the_local_rows(fleet, tmp_path, monkeypatch):
    pytest.importorskip("moto")
    import fsspec

    root, logs, local = fleet
    with moto_s3("fleet") as env:
        for k, v in env.items():
            monkeypatch.setenv(k, v)
        fs = fsspec.filesystem("s3")
        for p in logs:
            fs.put_file(str(p), f"fleet/day1/{p.relative_to(root)}")
        fs.put_file(str(root / "notes.txt"), "fleet/day1/notes.txt")
        sources = expand_sources(["s3://fleet/day1/"])
        assert sources == [f"s3://fleet/day1/{p.relative_to(root)}" for p in logs]
        table = tmp_path / "s3.csv"
        done = run_fleet(sources, FAST, jobs=2, table=str(table))
        assert [r.source for r in done.rows] == sources
        bad = next(r for r in done.rows if r.source.endswith("corrupt.tlog"))
        assert "s3://fleet/day1/b/corrupt.tlog" in bad.error and "mavcal-fleet-" not in bad.error
        assert_same_rows(comparable(read_table(table), "s3://fleet/day1"), comparable(local, str(root)))
        # a glob in a URL, and one object by its key
        assert expand_sources(["s3://fleet/day1/*/*.tlog"]) == [s for s in sources if s.count("/") == 5
                                                                and s.endswith(".tlog")]
        assert expand_sources(["s3://fleet/day1/a/sitl01.tlog"]) == ["s3://fleet/day1/a/sitl01.tlog"]


def test_a_file_whose_name_looks_like_a_glob_is_that_file(tmp_path):
    p = tmp_path / "log[1].tlog"
    p.write_bytes(b"x")
    assert expand_sources([str(p)]) == [str(p)]
    assert expand_sources([str(tmp_path)]) == [str(p)]


def test_an_http_directory_listing_gives_the_local_rows(fleet, tmp_path):
    """An http(s) server's directory listing (here Python's http.server on 127.0.0.1, read with
    fsspec's HTTPFileSystem): every log under it, recursively, each read by its worker, and the
    rows of the local files; a list file of URLs too."""
    import functools
    import http.server
    import threading

    pytest.importorskip("aiohttp")
    root, logs, local = fleet
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(root))
    handler.log_message = lambda *a, **k: None  # type: ignore[attr-defined]
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        base = f"http://127.0.0.1:{server.server_address[1]}"
        sources = expand_sources([f"{base}/"])
        assert sources == [f"{base}/{p.relative_to(root)}" for p in logs]  # notes.txt left out
        table = tmp_path / "http.csv"
        done = run_fleet(sources, FAST, jobs=2, table=str(table))
        assert [r.source for r in done.rows] == sources
        assert_same_rows(comparable(read_table(table), base), comparable(local, str(root)))
        lst = tmp_path / "urls.txt"
        lst.write_text(f"{base}/a/\n{base}/b/corrupt.tlog\n")
        assert expand_sources([f"@{lst}"]) == [s for s in sources if s.startswith(f"{base}/a/")] + [
            f"{base}/b/corrupt.tlog"]
    finally:
        server.shutdown()
        server.server_close()


def test_a_storage_error_is_that_log_s_row(tmp_path, monkeypatch, sitl_dir):
    """No credentials / no such key: a row for that log (exit 3), the others calibrated."""
    pytest.importorskip("moto")
    with moto_s3("fleet") as env:
        for k, v in env.items():
            monkeypatch.setenv(k, v)
        with pytest.raises(SourceError, match="s3://nobucket/"):
            expand_sources(["s3://nobucket/"])
        done = run_fleet(["s3://fleet/missing.tlog", str(sitl_dir / "sitl02.tlog")], FAST, jobs=1)
        bad, good = done.rows
        assert not bad.ok and bad.exit_code == 3 and "s3://fleet/missing.tlog" in bad.error and good.ok
