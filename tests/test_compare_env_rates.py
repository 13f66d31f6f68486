"""scripts/compare_env_rates.py refuses bad input by name before it checks anything out or times anything."""

import pytest
from conftest import import_script


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--ref", "HEAD", "SutureGym/NeedleInsert-v3"], "a pair is OLD_ID=NEW_ID, got 'SutureGym/NeedleInsert-v3'"),
        (["--ref", "HEAD", "=SutureGym/NeedleInsert-v3"], "a pair is OLD_ID=NEW_ID"),
        (["--ref", "no-such-ref", "a=b"], "--ref 'no-such-ref' is not a commit"),
        (["--ref", "HEAD", "--rounds", "0", "a=b"], "--rounds must be >= 1, got 0"),
    ],
)
def test_bad_arguments_are_named(monkeypatch, capsys, argv, message):
    script = import_script(monkeypatch, "compare_env_rates")
    with pytest.raises(SystemExit) as exit_info:
        script.main(argv)
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err
