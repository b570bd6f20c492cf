"""Data sets: download once from a server (a local HTTP server on 127.0.0.1 serving an archive built from the local
copy of the Silverbox files), SHA-256 checks, the cache, local folders, and the errors that say what to do."""

import hashlib
import http.server
import io
import socket
import threading
import zipfile

import numpy as np
import pytest

import rcotorch as rt
from rcotorch.data import datasets

FILES = ("SNLS80mV.csv", "Schroeder80mV.csv")


def _archive(folder, damage: str | None = None) -> bytes:
    """SilverboxFiles.zip as the benchmark ships it (files in a SilverboxFiles/ folder); ``damage`` flips one
    byte of that file."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("SilverboxFiles/", "")
        z.writestr("SilverboxFiles/README.txt", "Silverbox benchmark files\n")
        for name in FILES:
            data = bytearray((folder / name).read_bytes())
            if name == damage:
                data[1000] ^= 1
            z.writestr(f"SilverboxFiles/{name}", bytes(data))
    return buf.getvalue()


@pytest.fixture(scope="module")
def server(silverbox_csv):
    """An HTTP server on 127.0.0.1: /SilverboxFiles.zip, /damaged.zip (one byte of SNLS80mV.csv flipped),
    /page.html (a web page instead of the archive); it counts the requests per path."""
    folder = silverbox_csv.parent
    content = {"/SilverboxFiles.zip": _archive(folder), "/damaged.zip": _archive(folder, damage="SNLS80mV.csv"),
               "/page.html": b"<html><body>Virus scan warning</body></html>"}
    hits: dict[str, int] = {}

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self):
            hits[self.path] = hits.get(self.path, 0) + 1
            body = content.get(self.path)
            self.send_response(200 if body is not None else 404)
            self.send_header("Content-Length", str(len(body or b"")))
            self.end_headers()
            self.wfile.write(body or b"")

        def log_message(self, *args):
            pass

    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    base = f"http://127.0.0.1:{httpd.server_address[1]}"
    yield base, hits
    httpd.shutdown()
    httpd.server_close()


@pytest.fixture
def no_local(monkeypatch, tmp_path):
    """No local copy and an empty cache: the data set has to be downloaded."""
    monkeypatch.delenv("RCOTORCH_SILVERBOX", raising=False)
    monkeypatch.setenv("RCOTORCH_DATA", str(tmp_path / "cache"))
    return tmp_path / "cache" / "silverbox"


def _sha(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_download_once_verify_and_cache(server, no_local, silverbox_csv, capsys):
    base, hits = server
    url = f"{base}/SilverboxFiles.zip"
    files = rt.datasets.silverbox_files(urls=[url], progress=False)
    assert sorted(files) == sorted(FILES) and hits[url.removeprefix(base)] == 1
    for name, path in files.items():
        assert path.parent == no_local and _sha(path) == _sha(silverbox_csv.parent / name)
    assert sorted(p.name for p in no_local.iterdir()) == sorted(FILES)     # the archive is not kept
    assert "downloading the silverbox data set" in capsys.readouterr().err
    again = rt.datasets.silverbox_files(urls=[url], progress=False)       # from the cache
    assert again == files and hits["/SilverboxFiles.zip"] == 1
    rec = rt.datasets.silverbox(urls=[url], progress=False)
    assert rec.values.shape == (131072, 2) and rec.columns == ["V1", "V2"] and rec.units == {"V1": "V", "V2": "V"}
    assert rec.dt == pytest.approx(1 / 610.3515625)
    assert rec.metadata["splits"]["estimation"] == (40650, 105712)
    np.testing.assert_array_equal(rec.values, rt.load(silverbox_csv, columns=["V1", "V2"]).values)
    schroeder = rt.datasets.silverbox("Schroeder80mV", urls=[url], progress=False)
    assert schroeder.values.shape == (131072, 2) and "splits" not in schroeder.metadata
    with pytest.raises(rt.DataError, match=r"no record 'other'.*SNLS80mV"):
        rt.datasets.silverbox("other", urls=[url], progress=False)


def test_damaged_download_is_rejected_and_nothing_is_cached(server, no_local):
    base, _ = server
    with pytest.raises(rt.DataError) as e:
        rt.datasets.silverbox_files(urls=[f"{base}/damaged.zip"], progress=False)
    msg = str(e.value)
    assert "SNLS80mV.csv" in msg and "SHA-256" in msg and datasets.SILVERBOX.files["SNLS80mV.csv"] in msg
    assert "RCOTORCH_SILVERBOX" in msg                                       # what to do instead
    assert not no_local.exists() or not any(p.suffix == ".csv" for p in no_local.iterdir())


def test_a_web_page_instead_of_the_archive_falls_through_to_the_next_url(server, no_local):
    base, hits = server
    with pytest.raises(rt.DataError, match=r"page\.html: the answer is not a zip archive"):
        rt.datasets.silverbox_files(urls=[f"{base}/page.html"], progress=False)
    files = rt.datasets.silverbox_files(urls=[f"{base}/page.html", f"{base}/missing.zip",
                                              f"{base}/SilverboxFiles.zip"], progress=False)
    assert sorted(files) == sorted(FILES) and hits["/missing.zip"] == 1


def test_no_network_says_what_to_do(no_local):
    with socket.socket() as s:                       # a port on 127.0.0.1 where nothing listens
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(rt.DataError) as e:
        rt.datasets.silverbox_files(urls=[f"http://127.0.0.1:{port}/SilverboxFiles.zip"], progress=False)
    msg = str(e.value)
    assert "could not download SilverboxFiles.zip" in msg and f"127.0.0.1:{port}" in msg
    assert "Without network access" in msg and "RCOTORCH_SILVERBOX" in msg and "path=" in msg


def test_local_folder_by_argument_and_environment(tmp_path, monkeypatch, silverbox_csv):
    local = silverbox_csv.parent
    monkeypatch.delenv("RCOTORCH_SILVERBOX", raising=False)
    assert rt.datasets.silverbox_files(local)["SNLS80mV.csv"] == local / "SNLS80mV.csv"
    monkeypatch.setenv("RCOTORCH_SILVERBOX", str(local))
    assert rt.datasets.silverbox_files()["Schroeder80mV.csv"] == local / "Schroeder80mV.csv"

    partial = tmp_path / "partial"
    partial.mkdir()
    (partial / "SNLS80mV.csv").write_bytes((local / "SNLS80mV.csv").read_bytes())
    with pytest.raises(rt.DataError, match=r"partial \(path=\) has no Schroeder80mV.csv"):
        rt.datasets.silverbox_files(partial)
    monkeypatch.setenv("RCOTORCH_SILVERBOX", str(tmp_path / "nowhere"))
    with pytest.raises(rt.DataError, match=r"nowhere \(\$RCOTORCH_SILVERBOX\) does not exist"):
        rt.datasets.silverbox_files()

    (partial / "Schroeder80mV.csv").write_text("V1,V2\n0,0\n")
    with pytest.raises(rt.DataError, match=r"Schroeder80mV.csv .* has SHA-256 [0-9a-f]{64}, expected b22cbc.*"
                                           r"replace it with the file of the official SilverboxFiles.zip"):
        rt.datasets.silverbox_files(partial)


def test_a_damaged_cache_says_to_delete_it(server, no_local):
    base, _ = server
    files = rt.datasets.silverbox_files(urls=[f"{base}/SilverboxFiles.zip"], progress=False)
    with open(files["SNLS80mV.csv"], "ab") as f:
        f.write(b"0,0\n")
    with pytest.raises(rt.DataError, match=rf"SHA-256.*delete {no_local}"):
        rt.datasets.silverbox_files(urls=[f"{base}/SilverboxFiles.zip"], progress=False)


def test_the_scenario_reads_the_data_set(monkeypatch, silverbox_csv, tmp_path):
    from rcotorch.run.runner import Run
    monkeypatch.setenv("RCOTORCH_SILVERBOX", str(silverbox_csv.parent))
    run = Run("silverbox-cubic-stiffness", steps=10, out=tmp_path / "a")
    assert run.graph.blocks["data"].source == str(silverbox_csv.resolve())
    monkeypatch.setenv("RCOTORCH_SILVERBOX", str(tmp_path / "nowhere"))
    with pytest.raises(rt.DataError, match=r"silverbox-cubic-stiffness.*nowhere.*does not exist"):
        Run("silverbox-cubic-stiffness", steps=10, out=tmp_path / "b")
