"""docs/estimator.md §8's examples (the fused estimator's API) run as doctests: the section is the
API's documentation, so its examples must stay true."""

import doctest
import re
from pathlib import Path

DOC = Path(__file__).resolve().parents[3] / "docs" / "estimator.md"


def _section_8() -> str:
    text = DOC.read_text(encoding="utf-8")
    start = text.index("## 8. Moving sheets")
    end = text.find("\n## ", start + 1)
    section = text[start:] if end < 0 else text[start:end]
    return re.sub(r"^```.*$", "", section, flags=re.M)  # a fence closes an example's output


def test_the_fused_estimators_documented_examples_run():
    test = doctest.DocTestParser().get_doctest(_section_8(), {}, "estimator.md §8", str(DOC), 0)
    assert len(test.examples) >= 8  # the four API examples are there
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    runner.run(test)
    result = runner.summarize(verbose=False)
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples in docs/estimator.md §8 failed"
