from pathlib import Path

from sara.demo import run_demo


def test_demo_small(tmp_path: Path):
    table = run_demo(tmp_path / "demo", num_images=5, progress=False)  # 5 views: 10 pairs, each verified
    rows = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[2:-1]]
            for line in table.splitlines() if line.startswith("| ") and not line.startswith("| |")}
    assert rows["images registered"] == ["5/5", "5/5"]
    assert int(rows["pairs matched"][0]) <= int(rows["pairs matched"][1]) == 10
    assert float(rows["AUC@5"][0]) > 0.9
    assert (tmp_path / "demo" / "sara" / "sparse" / "0" / "images.bin").exists()
    report_html = tmp_path / "demo" / "sara" / "report.html"
    assert report_html.exists() and "<h2>View graph</h2>" in report_html.read_text(encoding="utf-8")
    assert f"Report: {report_html}" in table
