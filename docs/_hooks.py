"""mkdocs hooks (registered in mkdocs.yml under ``hooks:``).

The notebooks live in ``notebooks/`` at the repository root, where the tests execute them;
this hook adds them to the site as ``notebooks/*.ipynb`` pages without copying them into
``docs/``. It runs before mkdocs-jupyter's ``on_files``, which then renders them (not
executed: the stored cells as they are).
"""

from __future__ import annotations

from pathlib import Path

from mkdocs.plugins import event_priority
from mkdocs.structure.files import File, Files

NOTEBOOKS = "notebooks"


@event_priority(100)  # before mkdocs-jupyter (default priority 0) wraps the notebooks
def on_files(files: Files, config) -> Files:
    root = Path(config["config_file_path"]).parent
    for path in sorted((root / NOTEBOOKS).glob("*.ipynb")):
        uri = f"{NOTEBOOKS}/{path.name}"
        if files.get_file_from_path(uri) is None:
            # src_dir is the repository root, so that the file's source path is the notebook
            # itself (File.generated's virtual files lose it under mkdocs-jupyter's wrapper).
            files.append(
                File(
                    uri,
                    src_dir=str(root),
                    dest_dir=config["site_dir"],
                    use_directory_urls=config["use_directory_urls"],
                )
            )
    return files
