"""Outputs never land on inputs (same path, hard link, symbolic link) nor on existing outputs unless
asked to, and an image output's extension names the format written."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

from imaging.output_paths import (OutputPathError, check_new_file, check_not_inputs, check_output_folder,
                                  output_format)


@pytest.mark.parametrize("name, fmt", [("a.exr", "exr"), ("a.EXR", "exr"), ("a.pfm", "pfm"), ("a.hdr", "hdr"),
                                       ("a.rgbe", "hdr"), ("a.pic", "hdr"), ("a.png", "png"), ("dir.v2/a.Png", "png")])
def test_output_formats_by_extension(name: str, fmt: str) -> None:
    assert output_format(name) == fmt


@pytest.mark.parametrize("name, shown", [("a.jpg", "'.jpg'"), ("a.tif", "'.tif'"), ("a", "a file without an extension"),
                                         ("a.exr.bak", "'.bak'")])
def test_other_extensions_are_refused(name: str, shown: str) -> None:
    with pytest.raises(OutputPathError, match=f"{name}: cannot write {shown}: an output image's name must end in "
                                              r"\.exr, \.pfm, \.hdr \(\.rgbe, \.pic\) or \.png"):
        output_format(name)


@pytest.fixture
def source(tmp_path: Path) -> Path:
    (tmp_path / "in.exr").write_bytes(b"keep me")
    return tmp_path / "in.exr"


def test_same_path_in_any_spelling(tmp_path: Path, source: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "sub").mkdir()
    for output in (source, Path("in.exr"), Path("sub/../in.exr"), Path("./in.exr")):
        with pytest.raises(OutputPathError, match=r": is the input .*in.exr: refusing to overwrite it "
                                                  r"\(give --overwrite to replace it\)"):
            check_not_inputs([output], [source])
    check_not_inputs([source], [source], overwrite=True)


def test_hard_and_symbolic_links(tmp_path: Path, source: Path) -> None:
    os.link(source, tmp_path / "hard.exr")
    (tmp_path / "soft.exr").symlink_to(source)
    (tmp_path / "linked_dir").symlink_to(tmp_path, target_is_directory=True)
    with pytest.raises(OutputPathError, match=r"hard.exr: is a hard link to the input .*in.exr"):
        check_not_inputs([tmp_path / "hard.exr"], [None, source])
    with pytest.raises(OutputPathError, match=r"soft.exr: is a symbolic link to the input .*in.exr"):
        check_not_inputs([tmp_path / "soft.exr"], [source])
    with pytest.raises(OutputPathError, match=r"linked_dir/in.exr: is the input .*in.exr"):
        check_not_inputs([tmp_path / "linked_dir" / "in.exr"], [source])
    # the input given through a link, the output the file itself
    with pytest.raises(OutputPathError, match=r"in.exr: is the input .*soft.exr"):
        check_not_inputs([source], [tmp_path / "soft.exr"])


def test_other_files_and_missing_ones_pass(tmp_path: Path, source: Path) -> None:
    (tmp_path / "other.exr").write_bytes(b"keep me")  # equal content, another file
    check_not_inputs([tmp_path / "other.exr", tmp_path / "new.exr", tmp_path / "no" / "dir.exr"],
                     [source, tmp_path / "missing.exr", None])
    with pytest.raises(OutputPathError, match="new.exr: is the input"):  # neither exists: the paths decide
        check_not_inputs([tmp_path / "new.exr"], [tmp_path / "sub" / ".." / "new.exr"])


def test_a_symbolic_link_loop_is_one_line(tmp_path: Path, source: Path) -> None:
    (tmp_path / "a.exr").symlink_to(tmp_path / "b.exr")
    (tmp_path / "b.exr").symlink_to(tmp_path / "a.exr")
    with pytest.raises(OutputPathError, match=r"a.exr: a symbolic link loop"):
        check_not_inputs([tmp_path / "a.exr"], [source])


def test_an_existing_output_file_passes_only_with_overwrite(tmp_path: Path, source: Path) -> None:
    (tmp_path / "dangling.exr").symlink_to(tmp_path / "gone.exr")
    check_new_file(tmp_path / "new.exr")
    for path in (source, tmp_path / "dangling.exr"):  # a link counts, dangling or not
        with pytest.raises(OutputPathError, match=f"{path.name}: exists: refusing to replace it "
                                                  r"\(give --overwrite to replace it\)"):
            check_new_file(path)
        check_new_file(path, overwrite=True)
    for overwrite in (False, True):
        with pytest.raises(OutputPathError, match=f"{tmp_path.name}: is a folder"):
            check_new_file(tmp_path, overwrite)


def test_an_output_folder_holding_a_written_file_passes_only_with_overwrite(tmp_path: Path, source: Path) -> None:
    names = ("a.json", "b.exr", "c.png", "d.html", "e.csv")
    check_output_folder(tmp_path / "new", names)  # does not exist yet
    check_output_folder(tmp_path, names)  # holds in.exr, none of the names
    (tmp_path / "b.exr").write_bytes(b"")
    (tmp_path / "d.html").symlink_to(tmp_path / "gone.html")
    with pytest.raises(OutputPathError, match=r": holds an earlier run's files \(b.exr, d.html\): refusing to replace "
                                              r"them \(give --overwrite to replace them, or choose another --out\)"):
        check_output_folder(tmp_path, names)
    for name in ("a.json", "c.png", "e.csv"):
        (tmp_path / name).write_bytes(b"")
    with pytest.raises(OutputPathError, match=r"\(a.json, b.exr, c.png and 2 more\)"):
        check_output_folder(tmp_path, names)
    check_output_folder(tmp_path, names, overwrite=True)
    for overwrite in (False, True):  # a file where the folder goes: always
        with pytest.raises(OutputPathError, match="in.exr: exists and is not a folder; choose another --out"):
            check_output_folder(source, names, overwrite)
