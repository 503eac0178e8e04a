"""Inputs at scale: recursive folders, globs, list files, collision-free output keys."""

from __future__ import annotations

from pathlib import Path

import pytest

import torchiid.io.inputs as inputs
from torchiid.core.exceptions import TorchiidError
from torchiid.io.inputs import InputItem, list_inputs, read_list_file, unique_keys


def photo(path: Path) -> Path:
    """An empty file where an image would be: listing reads names, not pixels."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"")
    return path


@pytest.fixture
def library(tmp_path):
    """A photo library: two IMG_0001.png in different folders, a nested one, a text file."""
    root = tmp_path / "library"
    for name in ("2019/IMG_0001.png", "2020/IMG_0001.png", "2020/trip/IMG_0002.png"):
        photo(root / name)
    photo(root / "cover.png")
    (root / "2020" / "broken.png").write_text("not an image")
    (root / "2020" / "notes.txt").write_text("not an image either, and no image suffix")
    return root


def _keys(items):
    return [item.key for item in items]


def test_a_folder_is_flat_unless_recursive(library):
    assert _keys(list_inputs([library])) == ["cover"]
    items = list_inputs([library], recursive=True)
    assert _keys(items) == [
        "cover",
        "2019/IMG_0001",
        "2020/IMG_0001",
        "2020/broken",
        "2020/trip/IMG_0002",
    ]
    assert items[1].path == library / "2019" / "IMG_0001.png"
    assert items[4].stem == "IMG_0002" and items[4].folder == "2020/trip"
    unique_keys(items)  # two IMG_0001 in different folders do not collide


def test_recursive_listing_skips_hidden_folders_and_the_output_folder(library):
    (library / ".thumbnails").mkdir()
    photo(library / ".thumbnails" / "t.png")
    out = library / "out"
    photo(out / "cover-reflectance.png")  # outputs of an earlier run inside the input folder
    keys = _keys(list_inputs([library], recursive=True, exclude=[out]))
    assert not [k for k in keys if k.startswith(("out/", ".thumbnails"))]
    assert "out/cover-reflectance" in _keys(list_inputs([library], recursive=True))


def test_hidden_files_are_skipped_with_or_without_recursion(library):
    photo(library / "._cover.png")  # macOS's AppleDouble file beside the photo
    for recursive in (False, True):
        keys = _keys(list_inputs([library], recursive=recursive))
        assert "cover" in keys and "._cover" not in keys
    assert _keys(list_inputs([library / "._cover.png"])) == ["._cover"]  # named on its own


def test_globs_keep_the_folders_below_their_fixed_part(library, monkeypatch):
    monkeypatch.chdir(library.parent)
    items = list_inputs(["library/*/IMG_0001.png", "library/**/IMG_0002.png"])
    assert _keys(items) == ["2019/IMG_0001", "2020/IMG_0001", "2020/trip/IMG_0002"]
    assert _keys(list_inputs(["library/20*/*"])) == [
        "2019/IMG_0001",
        "2020/IMG_0001",
        "2020/broken",
    ]  # image suffixes only: notes.txt and folders are not taken
    with pytest.raises(TorchiidError, match=r"library/\*\.jpg: no image file matches"):
        list_inputs(["library/*.jpg"])


def test_an_existing_name_is_never_a_pattern(tmp_path):
    odd = photo(tmp_path / "shot[1].png")
    assert list_inputs([odd]) == [InputItem(odd, "shot[1]")]


def test_text_list_relative_to_its_folder(library, tmp_path, monkeypatch):
    listing = library / "list.txt"
    listing.write_text(
        "# my selection\n2019/IMG_0001.png\n\n2020/IMG_0001.png\n"
        f"{library / '2020' / 'trip' / 'IMG_0002.png'}\n"
    )
    monkeypatch.chdir(tmp_path)  # relative paths follow the list, not the working folder
    items = read_list_file(listing)
    assert _keys(items) == ["2019/IMG_0001", "2020/IMG_0001", "2020/trip/IMG_0002"]
    assert all(item.path.is_file() for item in items)


def test_csv_list_with_masks(library):
    mask = library / "masks" / "m.png"
    mask.parent.mkdir()
    mask.write_bytes(b"x")
    listing = library / "list.csv"
    listing.write_text("id,path,mask\n1,2019/IMG_0001.png,masks/m.png\n2,cover.png,\n")
    items = read_list_file(listing)
    assert _keys(items) == ["2019/IMG_0001", "cover"]
    assert items[0].mask == library / "masks" / "m.png" and items[1].mask is None


@pytest.mark.parametrize(
    "name, content, message",
    [
        ("missing.txt", None, "missing.txt: no such list file"),
        ("nopath.csv", "file,mask\na.png,\n", "a CSV list needs a 'path' column (columns: 'file'"),
        ("emptypath.csv", "path\n\n,\n", "emptypath.csv: line 3: empty path"),
        ("empty.txt", "# nothing\n\n", "empty.txt: the list names no image"),
        ("latin1.txt", "caf\xe9.png\n".encode("latin-1"), "latin1.txt: not a UTF-8 text file"),
    ],
)
def test_bad_list_files_are_one_line_errors(tmp_path, name, content, message):
    path = tmp_path / name
    if isinstance(content, bytes):
        path.write_bytes(content)
    elif content is not None:
        path.write_text(content)
    with pytest.raises(TorchiidError, match=message.replace("(", r"\(").replace(")", r"\)")):
        list_inputs([], lists=[path])


def test_two_inputs_with_one_key_are_refused_repeats_dropped(library):
    a = library / "2019" / "IMG_0001.png"
    b = library / "2020" / "IMG_0001.png"
    assert unique_keys(list_inputs([a, a])) == [InputItem(a, "IMG_0001")]
    with pytest.raises(TorchiidError, match="two inputs would write the same outputs"):
        unique_keys(list_inputs([a, b]))  # named on their own, both are IMG_0001


def test_a_large_folder_is_listed_in_one_pass(tmp_path, monkeypatch, counting_os):
    folder = tmp_path / "many"
    folder.mkdir()
    n = 200  # the counts below do not grow with n: any n shows it
    for i in range(n):
        (folder / f"{i:05d}.jpg").write_bytes(b"")
    counting = counting_os("scandir", "listdir", "stat", "lstat", "samefile")  # torchiid.io.inputs
    monkeypatch.setattr(inputs, "os", counting)
    items = unique_keys(list_inputs([folder], recursive=True))
    assert len(items) == n and items[0].key == "00000"
    assert items[-1].key == f"{n - 1:05d}" and Path(items[-1].path).parent == folder
    # one listing of the folder; no call per file (a stat each, or comparisons of pairs)
    assert counting.calls["scandir"] + counting.calls["listdir"] == 1
    assert counting.calls["stat"] + counting.calls["lstat"] <= 2
    assert counting.calls["samefile"] == 0


def test_globs_leave_out_the_output_folder(library, monkeypatch):
    monkeypatch.chdir(library.parent)
    out = library / "out"
    photo(out / "cover-reflectance.png")  # outputs of an earlier run
    photo(out / "2019" / "IMG_0001-reflectance.png")
    keys = _keys(list_inputs(["library/**/*.png"], exclude=[Path("library/out")]))
    assert "2020/trip/IMG_0002" in keys and not [k for k in keys if k.startswith("out/")]
    assert "out/cover-reflectance" in _keys(list_inputs(["library/**/*.png"]))
    # a glob whose fixed part is the output folder names its files on purpose
    assert _keys(list_inputs(["library/out/*.png"], exclude=[out])) == ["cover-reflectance"]


def test_files_to_skip_are_left_out_of_walks_and_globs_but_not_named_ones(library, monkeypatch):
    from torchiid.io.inputs import file_identity

    monkeypatch.chdir(library.parent)
    written = photo(library / "cover-reflectance.png")  # an earlier run's, into the same folder
    skip = {file_identity(written)}
    assert _keys(list_inputs([library], skip=skip)) == ["cover"]
    assert _keys(list_inputs([Path("library")], recursive=True, skip=skip))[0] == "cover"
    assert _keys(list_inputs(["library/*.png"], skip=skip)) == ["cover"]
    assert _keys(list_inputs([written], skip=skip)) == ["cover-reflectance"]  # named on its own
    assert sorted(_keys(list_inputs([library]))) == ["cover", "cover-reflectance"]
    # the folder through a symbolic link, and by a name with "..": the same files
    (library.parent / "link").symlink_to(library, target_is_directory=True)
    assert _keys(list_inputs([Path("link")], skip=skip)) == ["cover"]
    assert _keys(list_inputs(["link/*.png"], skip=skip)) == ["cover"]
    assert _keys(list_inputs([library / "2019" / ".."], skip=skip)) == ["cover"]
    assert file_identity("link/cover-reflectance.png") == file_identity(written)


def test_walks_into_says_whether_a_folder_is_listed(library, monkeypatch):
    from torchiid.io.inputs import walks_into

    monkeypatch.chdir(library.parent)
    out = library / "out"
    out.mkdir()
    assert walks_into([library], library) and walks_into(["library/*.png"], library)
    assert walks_into(["library/out/**/*.png"], out) and walks_into([out], library)
    assert not walks_into([library], out)  # from above: the output folder is excluded
    assert not walks_into(["library/**/*.png", library / "cover.png"], out)


def test_names_that_differ_only_in_case_are_refused(tmp_path):
    a = photo(tmp_path / "a" / "IMG_0001.png")
    b = photo(tmp_path / "b" / "img_0001.png")
    with pytest.raises(TorchiidError, match=r"same outputs \(names that differ only in case\)"):
        unique_keys(list_inputs([a, b]))  # one set of files on a case-insensitive disk
