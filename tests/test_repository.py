"""A clone from a forge stands alone: the documents it links are in it, its licence agrees with
pyproject, and it says which data and weights carry their own terms."""

import re
import tomllib

from tests.conftest import REPO, SHARED

README = (REPO / "README.md").read_text()
LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")


def test_markdown_links_stay_inside_the_repository():
    for doc in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]:
        for target in LINK.findall(doc.read_text()):
            if re.match(r"[a-z]+://", target):
                continue
            path = (doc.parent / target).resolve()
            assert path.is_relative_to(REPO), f"{doc.name} links {target}, outside the repository"
            assert path.exists(), f"{doc.name} links {target}, which does not exist"
    assert "](docs/method.md)" in README


def test_the_method_page_cites_the_thesis_tables():
    method = (REPO / "docs" / "method.md").read_text()
    for table in ("3.1", "3.3", "4.1", "4.2", "5.1", "6.1", "6.2", "6.4"):
        assert f"table {table}" in method, table
    for figure in ("0.47", "0.076", "78.4", "89.1", "58.3", "75.9"):
        assert figure in method, figure
    assert "MBVLAD" in method and "ORB-MBVLAD" in method and "SVM" in method and "Recall@N" in method


def test_licence_agrees_with_pyproject():
    pyproject = tomllib.loads((REPO / "pyproject.toml").read_text())
    assert pyproject["project"]["license"] == {"text": "MIT"}
    assert (REPO / "LICENSE").read_text().startswith("MIT License")


def test_readme_names_the_terms_of_data_and_weights():
    section = README[README.index("## Licence, and the data and weights") :]
    assert "SqueezeNet" in section and "BSD 2-Clause" in section
    assert "XFeat" in section and "Apache-2.0" in section
    assert "penn-campus-gps" in section and "do not redistribute" in section
    # The facts come from the files beside the data and weights; they say so still.
    assert "do not redistribute" in (SHARED / "data" / "penn-campus-gps" / "SOURCE.txt").read_text()
    squeeze = SHARED / "models" / "squeezenet1.1" / "caffe-openvino-ir"
    assert (squeeze / "LICENSE.DeepScale-SqueezeNet.BSD-2-Clause").exists()
