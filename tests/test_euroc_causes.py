

def test_without_flights_the_bench_says_where_to_put_them(tmp_path, monkeypatch):
    monkeypatch.setenv("VTOLPOSE_EUROC_DATA", str(tmp_path))
    lines: list[str] = []
    assert bench_euroc_causes(lines.append) == []
    assert len(lines) == 1 and "skipped" in lines[0] and "VTOLPOSE_EUROC_DATA" in lines[0]
