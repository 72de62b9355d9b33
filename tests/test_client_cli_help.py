"""articast-print and articast-record --help: their real names, what url and session are, and
how to give a token (they showed `python -m articast.client...` and bare `url session`)."""

import pytest

from articast.client import print as print_cmd
from articast.client import record as record_cmd


@pytest.mark.parametrize("module, name", [(print_cmd, "articast-print"),
                                          (record_cmd, "articast-record")])
def test_usage_names_the_command_and_teaches_url_session_and_token(module, name, capsys):
    with pytest.raises(SystemExit) as done:
        module.main(["--help"])
    assert done.value.code == 0
    text = capsys.readouterr().out
    assert text.startswith(f"usage: {name} ")
    assert "python -m" not in text.split("\n\n")[0]  # the usage line is the command's own
    positional = text.split("positional arguments:")[1].split("options:")[0]
    assert "ws://HOST:PORT/ws" in positional.split("session")[0]  # url explained
    assert "'demo'" in positional and "/api/sessions" in positional  # session explained
    assert "?token=TOKEN" in text and "ARTICAST_TOKEN" in text
