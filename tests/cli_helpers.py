"""Helpers of the tests that drive the polydem command in this process."""

from pathlib import Path

from polydem.cli import main


def write_scene(folder, text, name="scene.toml", replace=()):
    """``text`` with each (old, new) of ``replace`` substituted (old must occur), written to ``folder/name``."""
    for old, new in replace:
        assert old in text, old
        text = text.replace(old, new)
    path = Path(folder) / name
    path.write_text(text)
    return path


def run(args, capsys):
    """main(args) in this process: (exit code, stdout, stderr)."""
    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return code, out, err
