"""data_schema.atomic: a target keeps its old content or holds the complete new one; no temporary file is left."""
import pytest

from data_schema import atomic


def test_write_text_replaces_whole_and_leaves_nothing_beside(tmp_path):
    target = tmp_path / "sub" / "report.json"
    atomic.write_text(target, "old")
    atomic.write_text(target, "new content")
    assert target.read_text() == "new content"
    assert [p.name for p in target.parent.iterdir()] == ["report.json"]


def test_failed_writer_keeps_old_content_and_removes_its_temporary(tmp_path):
    target = tmp_path / "report.json"
    target.write_text("old")
    with pytest.raises(RuntimeError, match="midway"):
        with atomic.replacing(target) as tmp:
            tmp.write_text("half")
            assert tmp.parent == target.parent and tmp.name.endswith(atomic.TMP_SUFFIX)
            raise RuntimeError("midway")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["report.json"]


def test_concurrent_writers_get_distinct_temporaries(tmp_path):
    target = tmp_path / "x.txt"
    with atomic.replacing(target) as a, atomic.replacing(target) as b:
        assert a != b
        a.write_text("a")
        b.write_text("b")
    assert target.read_text() == "a"  # the outer block ends last: its content wins, whole


def test_write_csv_comments_header_rows_and_ignored_keys(tmp_path):
    target = tmp_path / "t.csv"
    atomic.write_csv(target, [{"a": 1, "b": "x", "extra": 9}, {"a": 2, "b": "y"}], ["a", "b"], comments=["made by"])
    assert target.read_text().splitlines() == ["# made by", "a,b", "1,x", "2,y"]
    assert [p.name for p in tmp_path.iterdir()] == ["t.csv"]
