"""Write docs/config.md, the render config reference, from the pydantic models.

    python scripts/make_config_docs.py

tests/test_cli_hostile.py checks that the committed file is current.
"""

from pathlib import Path

from torchraster.config import config_reference

if __name__ == "__main__":
    out = Path(__file__).resolve().parents[1] / "docs" / "config.md"
    out.write_text(config_reference() + "\n")
    print(f"wrote {out}")
