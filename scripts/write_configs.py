"""Write ``configs/NAME.yaml`` for every zoo entry (run after changing an entry in ``occkit/zoo/<family>.py``).

    python scripts/write_configs.py
"""

from __future__ import annotations

from pathlib import Path

from occkit import zoo


def main() -> None:
    folder = Path(__file__).resolve().parents[1] / "configs"
    folder.mkdir(exist_ok=True)
    for name in zoo.names():
        path = folder / f"{name}.yaml"
        path.write_text(zoo.config_yaml(name))
        print(f"wrote {path.relative_to(folder.parent)}")


if __name__ == "__main__":
    main()
