"""`python -m motorjig.sim` options: each driver's variant and the jig's protocol."""

import pytest

from motorjig.sim import __main__ as sim_main


def test_driver_variants_and_jig_protocol_are_parsed():
    a = sim_main.parse_args(["--drivers", "2,3:v8,4:V6", "--jig-protocol", "8"])
    assert tuple(a.drivers) == (2, 3, 4) and a.drivers.ver8 == (3,) and a.jig_protocol == 8
    a = sim_main.parse_args([])
    assert tuple(a.drivers) == (2, 3) and a.drivers.ver8 == () and a.jig_protocol == 6


@pytest.mark.parametrize("argv,msg", [
    (["--drivers", "2,3:v7"], "variant must be v6 or v8"),
    (["--drivers", "2,16"], "must be 0..15"),
    (["--drivers", "2,2:v8"], "given twice"),
    (["--drivers", "a"], "expected ids"),
    (["--jig-protocol", "7"], "must be 6 or 8"),
])
def test_bad_options_are_one_clear_error(argv, msg, capsys):
    with pytest.raises(SystemExit) as exc:
        sim_main.parse_args(argv)
    assert exc.value.code == 2 and msg in capsys.readouterr().err


def test_bench_prints_the_variants_and_the_demo_finds_them(capsys):
    rc = sim_main.main(["--drivers", "2,3:v8", "--jig-protocol", "8", "--no-pty", "--duration", "0.1"])
    out = capsys.readouterr().out
    assert rc == 0
    assert "jig = slave 1 (protocol Ver8), drivers 2 (Ver6), 3 (Ver8)" in out
    assert "id  1: Ver8  MotorJig bridge" in out
    assert "id  2: Ver6  Ezi-STEP" in out and "id  3: Ver8  Ezi-STEP" in out
    assert "pos  10000" in out  # the demo's move on driver 2 completed
