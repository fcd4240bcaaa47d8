"""docs/configuration.md is generated from Settings: it must be current and complete."""

from __future__ import annotations

from pathlib import Path

from service import config_docs
from service.config import Settings

PAGE = Path(__file__).resolve().parents[1] / "docs" / "configuration.md"


def test_every_setting_has_a_section_and_a_description() -> None:
    assert config_docs.unplaced() == set()
    listed = [name for names in config_docs.SECTIONS.values() for name in names]
    assert len(listed) == len(set(listed)), "a setting is listed in two sections"
    assert set(listed) <= set(Settings.model_fields), "a section lists an unknown setting"
    assert [n for n, f in Settings.model_fields.items() if not f.description] == []


def test_the_page_is_current() -> None:
    assert PAGE.read_text() == config_docs.render(), (
        "docs/configuration.md is stale: run `python -m service.config_docs > "
        "docs/configuration.md`"
    )


def test_the_page_shows_defaults_as_typed() -> None:
    page = config_docs.render()
    assert "| `LOOPNET_DATA_DIR` | `./loopnet-data` |" in page
    assert "| `LOOPNET_REDIS_URL` | unset |" in page
    assert "| `LOOPNET_OFFLINE` | `false` |" in page
