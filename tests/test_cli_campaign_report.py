"""The campaign results page's rotation-sense table (issue 37 item 4)."""

from __future__ import annotations

from msmill.cli.campaign_report import sense_table
from msmill.machine import rotation_senses


def test_sense_table_predicts_each_sense_with_its_own_surrogate_and_names_the_others(monkeypatch, tmp_path):
    """One row per sense; a sense with a surrogate gets the UG2 prediction made with that sense's file (here
    up_up's is a 16-run surrogate fitted for the test: its row must show 16 runs and another P80), the
    others say none is shipped."""
    import msmill.model.providers as pv
    from msmill.surrogate import persist
    from msmill.surrogate.stage_model import StageSurrogate

    real = pv.sense_surrogate_path
    runs = persist.load(real("down_down")).training_.runs
    small = persist.save(StageSurrogate(n_restarts=0).fit(runs[::8][:16]), tmp_path / "up_up.json")
    monkeypatch.setattr(pv, "sense_surrogate_path",
                        lambda s: real(s) if s == "down_down" else small if s == "up_up" else None)
    rows = sense_table()
    body = [r for r in rows[2:] if r.startswith("| ")]
    assert [r.split("|")[1].strip() for r in body] == list(rotation_senses())
    cells = {r.split("|")[1].strip(): [c.strip() for c in r.split("|")[2:-1]] for r in body}
    assert cells["down_up"][0] == "none shipped" and not any(cells["down_up"][1:])
    down, up = cells["down_down"], cells["up_up"]
    assert int(down[0]) >= 100 and up[0] == "16"  # runs of the file each sense used
    for row in (down, up):
        p80, (lo, hi) = float(row[1]), map(float, row[2].split("-"))
        assert lo <= p80 <= hi and 10 < p80 < 25  # UG2's P80 (mm) inside its band
        assert 0 < float(row[4]) < 5 and 0 < float(row[6]) < 5  # residence (s), impact energy (kWh/t)
    assert up[1:] != down[1:]
