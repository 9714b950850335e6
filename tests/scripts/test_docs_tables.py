"""The docs' option tables are those the config dataclasses make (scripts/docs_tables.py)."""

import importlib.util
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
spec = importlib.util.spec_from_file_location("docs_tables", ROOT / "scripts" / "docs_tables.py")
docs_tables = importlib.util.module_from_spec(spec)
spec.loader.exec_module(docs_tables)

#: every config whose fields make a command's flags (docs/layout.md, "One source for every setting")
FLAG_CONFIGS = {"gensplat_transforms.settings:GenSplatConfig", "gensplat_transforms.training:TrainConfig",
                "gensplat_transforms.geometry.model.losses:LossWeights", "gensplat_sim.world:WorldConfig",
                "gensplat_sim.record:RecordConfig", "gensplat_sim.demo:DemoConfig"}  # fmt: skip


def test_every_table_in_the_docs_is_up_to_date():
    stale = docs_tables.stale()
    assert not stale, f"run `python scripts/docs_tables.py`: out of date {sorted(p.name for p in stale)}"


def test_every_config_with_flags_has_a_table():
    marked = {f"{m}:{c}" for p in docs_tables.DOCS.glob("*.md")
              for m, c in re.findall(r"<!-- options: ([\w.]+):(\w+) -->", p.read_text())}  # fmt: skip
    assert FLAG_CONFIGS <= marked, FLAG_CONFIGS - marked


def test_a_stale_table_is_found_rewritten_and_checked(tmp_path, capsys, monkeypatch):
    doc = tmp_path / "x.md"
    doc.write_text("intro\n<!-- options: gensplat_transforms.geometry.model.losses:LossWeights -->\n| old |\n"
                   "<!-- /options -->\nafter\n")  # fmt: skip
    assert list(docs_tables.stale(tmp_path)) == [doc]
    monkeypatch.setattr(docs_tables, "DOCS", tmp_path)
    assert docs_tables.main(["--check"]) == 1 and "| old |" in doc.read_text()
    assert docs_tables.main([]) == 0
    text = doc.read_text()
    assert "| old |" not in text and "`--l-depth`" in text and text.endswith("<!-- /options -->\nafter\n")
    assert docs_tables.main(["--check"]) == 0


def test_a_marker_naming_a_missing_class_fails_loudly(tmp_path):
    (tmp_path / "x.md").write_text("<!-- options: gensplat_transforms.settings:NoSuchConfig -->\n<!-- /options -->\n")
    with pytest.raises(AttributeError, match="NoSuchConfig"):
        docs_tables.stale(tmp_path)


@pytest.mark.parametrize("text", ["<!-- options: gensplat_transforms.settings:GenSplatConfig -->\n| left open |\n",
                                  "<!-- /options -->\n",
                                  "<!-- options: gensplat_transforms.settings:GenSplatConfig --> <!-- /options -->\n",
                                  "<!-- options: gensplat_transforms.settings:GenSplat Config -->\n<!-- /options -->\n"])
def test_markers_that_do_not_pair_are_refused_with_the_file_named(tmp_path, text):
    (tmp_path / "y.md").write_text(text)
    with pytest.raises(ValueError, match=r"y\.md: .*each table needs both"):
        docs_tables.stale(tmp_path)
