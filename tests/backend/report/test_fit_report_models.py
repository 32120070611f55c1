"""The fit report reads the search model's evaluations apart from the model of record's."""
from relief_bsdf.report.fit_report import _iterations_html, stop_verdict


def _doc():
    it = [{"parameters": {"height_scale": 1.0, "filter_sigma_um": 0.0}, "rms": 3.0, "search": 1.0, "model": "search"},
          {"parameters": {"height_scale": 1.1, "filter_sigma_um": 0.0}, "rms": 2.0, "search": 2.0, "model": "record"},
          {"parameters": {"height_scale": 1.2, "filter_sigma_um": 0.0}, "rms": 1.5, "search": 1.7, "model": "record"}]
    return {"iterations": it, "stopped": "converged", "algorithm": "Gauss-Newton"}


def test_best_marker_on_the_model_of_record():
    html = _iterations_html(_doc())
    rows = html.split("<tr")
    marked = [r for r in rows if "best of the model of record" in r]
    assert len(marked) == 1
    assert "1.2" in marked[0] and "record" in marked[0]      # not the search model's lower objective


def test_without_models_every_evaluation_is_of_record():
    doc = _doc()
    for it in doc["iterations"]:
        del it["model"]
    marked = [r for r in _iterations_html(doc).split("<tr") if "best of the model of record" in r]
    assert len(marked) == 1 and ">1<" in marked[0].replace(" ", "")       # the lowest search objective, row 1


def test_stop_verdict_counts_only_the_model_of_record():
    doc = _doc()
    doc["iterations"] = doc["iterations"] * 3          # 9 evaluations, 3 of them on the search model
    _, sentence = stop_verdict(doc)
    assert "model of record" in sentence
    assert "Converged after 9 evaluations" in sentence
