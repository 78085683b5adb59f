"""Bad input, narf-view: runs it cannot show, hosts it cannot serve on, a busy port (said, not hidden). Each case:
exit code 2 and one ``narf-view: error:`` line, no server left listening."""

import os
import socket

import browser


def test_view_refuses_a_run_it_cannot_show(tmp_path, capsys):
    from pipelines.cli import view
    from pipelines.cli.common import run_cli

    port = browser.free_port()
    assert run_cli("narf-view", view.main, ["--run", str(tmp_path / "missing"), "--port", str(port)]) == 2
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "checkpoint.pt").write_bytes(b"not a checkpoint")
    assert run_cli("narf-view", view.main, ["--run", str(foreign), "--port", str(port)]) == 2
    errors = capsys.readouterr().err.strip().splitlines()
    assert len(errors) == 2 and all(line.startswith("narf-view: error: ") for line in errors)
    with socket.socket() as s:  # no server was left listening
        s.bind(("127.0.0.1", port))


def test_a_busy_port_is_said_and_a_foreign_host_refused(tiny_run, capsys):
    import socket
    import subprocess
    import sys

    import spawn

    from pipelines.cli import view
    from pipelines.cli.common import run_cli

    for host, message in (("no-such-host.invalid", "the name does not resolve"), ("192.0.2.1", "not an address")):
        assert run_cli("narf-view", view.main, ["--run", str(tiny_run), "--host", host]) == 2  # at once, no server
        assert message in capsys.readouterr().err
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        argv = [sys.executable, "-c", "from pipelines.cli.view import entrypoint; entrypoint()"]
        argv += ["--run", str(tiny_run), "--port", str(port)]
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        proc = spawn.popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
        out, err = spawn.Reader(proc.stdout), spawn.Reader(proc.stderr)
        browser.wait(lambda: "serving" in out.text() or proc.poll() is not None or None, 120, "the server to start")
        proc.terminate()
        spawn.finish(proc, 30, "narf-view")
    err.thread.join(timeout=5)
    assert f"port {port} is busy; serving on port" in err.text()
