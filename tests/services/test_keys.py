"""``hydrosoft-stack keys generate``: a host's key pair, its secret readable by its owner only, never overwritten."""

import stat

import pytest
import zmq.auth

from hydrosoft.services.bus import sockets as b
from hydrosoft.services.commands import keys
from hydrosoft.services.commands.cli import main


def test_keys_generate_writes_a_pair_whose_secret_only_its_owner_may_read(tmp_path, capsys):
    folder = tmp_path / "keys"
    assert main(["keys", "generate", str(folder), "--host", "robot"]) == keys.EXIT_OK
    public, secret = folder / "robot.key", folder / "robot.key_secret"
    assert stat.S_IMODE(secret.stat().st_mode) == 0o600
    assert stat.S_IMODE(public.stat().st_mode) == 0o644
    public_key, secret_key = zmq.auth.load_certificate(secret)
    assert secret_key is not None and zmq.auth.load_certificate(public) == (public_key, None)
    b.check_secret_key_file(secret)  # the bus accepts it as written
    assert "robot.key_secret" in capsys.readouterr().out


def test_keys_generate_never_overwrites_a_pair(tmp_path, capsys):
    public, secret = keys.generate_key_pair(tmp_path, "compute")
    before = secret.read_bytes()
    assert main(["keys", "generate", str(tmp_path), "--host", "compute"]) == keys.EXIT_FAILED
    assert "compute.key exists" in capsys.readouterr().err
    assert secret.read_bytes() == before


@pytest.mark.parametrize("host", ["", "../robot", "robot pc", "a" * 65])
def test_keys_generate_refuses_a_host_name_that_is_not_a_plain_name(tmp_path, host):
    with pytest.raises(keys.KeyPairError, match="host name"):
        keys.generate_key_pair(tmp_path, host)
    assert not any(tmp_path.iterdir())
