"""``snds app`` on the command line: its one-line errors."""

from __future__ import annotations

import socket
import sys

import pytest

from snds.cli import main


def test_a_port_in_use_is_one_line_and_exit_2(capsys) -> None:
    pytest.importorskip("uvicorn", reason="snds app needs the app extra")
    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = taken.getsockname()[1]
        assert main(["app", "--port", str(port)]) == 2
    error = capsys.readouterr().err
    assert error.startswith(f"snds: error: cannot listen on 127.0.0.1:{port}: ")
    assert error.count("\n") == 1


def test_without_the_app_extra_snds_app_says_what_to_install(monkeypatch, capsys) -> None:
    # GIVEN an environment without Starlette (a blocked import) and snds.app not yet imported
    for name in list(sys.modules):
        if name.split(".")[0] == "starlette" or name.startswith("snds.app"):
            monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "starlette", None)
    # WHEN snds app runs THEN one line names the extra
    assert main(["app"]) == 2
    error = capsys.readouterr().err
    # Uninstalled, Python names the package; blocked here, the submodule it reached first.
    assert error.startswith("snds: error: snds app needs the app extra (starlette")
    assert error.endswith(" is missing): pip install 'snds[app]'\n")
