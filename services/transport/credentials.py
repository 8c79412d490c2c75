"""Who may talk to a run: Zenoh's own mutual TLS and access control.

By default a run's sessions are peers on loopback TCP, and any process that
reaches a port can publish into the run or read it.  With a run's credentials
(``make_credentials``: a certificate authority of the run's own, a certificate
for the router and one per role, made with ``openssl``) the runner's session is
a Zenoh router that accepts only TLS links whose client certificate that CA
signed (``enable_mtls``), and whose access control lets only the run's roles
(the certificates' common names) put, subscribe, query, reply and hold
liveliness tokens, and only under ``etar/<run_id>/``.  Every service is a client
of that router with its role's certificate; nothing listens in the clear.

A peer without the run's credentials is refused at the TLS handshake (no
certificate, or one another CA signed); one with a certificate of the right CA
but another name gets a session whose traffic the router drops.

The command that makes the credentials is ``etar-bench certs DIR`` (docs/cli.md);
``openssl_commands`` prints the openssl calls it makes.
"""

from __future__ import annotations

import ipaddress
import json
import shutil
import subprocess
from pathlib import Path

from services.runtime import topics
from services.runtime.roles import CREDENTIAL_NAMES as ROLES
from services.transport.session import ZenohOptions

DAYS = 30
# the run's traffic, all of it under etar/<run_id>/: what the roles may do there
MESSAGES = ["put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
            "liveliness_token", "liveliness_query", "declare_liveliness_subscriber"]


class CredentialsError(ValueError):
    """Credentials that cannot be made or used; the message names the file."""


def _run(cmd: list[str], cwd: Path, stdin: bytes | None = None) -> None:
    done = subprocess.run(cmd, cwd=cwd, input=stdin, capture_output=True)
    if done.returncode != 0:
        raise CredentialsError(f"openssl failed in {cwd}: {' '.join(cmd)}: "
                               f"{done.stderr.decode(errors='replace').strip().splitlines()[-1:]}")


def openssl_commands(name: str) -> list[list[str]]:
    """The openssl calls that issue one certificate (``name``.pem/.key, common name
    ``name``, extensions from ``name``.ext) signed by ca.pem."""
    return [
        ["openssl", "req", "-new", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
         "-subj", f"/CN={name}", "-keyout", f"{name}.key", "-out", f"{name}.csr"],
        ["openssl", "x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial",
         "-days", str(DAYS), "-out", f"{name}.pem", "-extfile", f"{name}.ext"],
    ]


def make_credentials(out, hosts=("127.0.0.1",), roles=ROLES) -> Path:
    """A run's credentials in ``out``: ca.pem (and ca.key, which signs), router.pem/.key
    valid for every address in ``hosts`` (and localhost), and <role>.pem/.key per role
    (common name = the role).  Returns ``out``."""
    if shutil.which("openssl") is None:
        raise CredentialsError("openssl is not installed (Debian: apt install openssl)")
    out = Path(out)
    for h in hosts:
        try:
            ipaddress.ip_address(h)
        except ValueError:
            raise CredentialsError(f"host {h!r}: expected an IP address (the router's certificate names it)") from None
    for r in roles:
        if not r or not all(c.isalnum() or c in "_-" for c in r):
            raise CredentialsError(f"role {r!r}: use letters, digits, '_' or '-'")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CredentialsError(f"{out}: cannot make the credentials' folder there "
                               f"({'a file of that name exists' if out.is_file() else exc.strerror or exc})") from None
    if not ((out / "ca.pem").is_file() and (out / "ca.key").is_file()):
        _run(["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
              "-days", str(DAYS), "-subj", "/CN=etar-run-ca", "-keyout", "ca.key", "-out", "ca.pem",
              "-addext", "basicConstraints=critical,CA:TRUE", "-addext", "keyUsage=critical,keyCertSign,cRLSign"],
             out)
    san = ",".join(["DNS:localhost"] + [f"IP:{h}" for h in hosts])
    # rustls (Zenoh's TLS) wants v3 leaves with these extensions; serverAuth and the
    # addresses on every certificate, so that any role can also listen
    for name in ("router", *roles):
        (out / f"{name}.ext").write_text("basicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature\n"
                                         f"extendedKeyUsage=serverAuth,clientAuth\nsubjectAltName={san}\n")
        for cmd in openssl_commands(name):
            _run(cmd, out)
        (out / f"{name}.csr").unlink()
        (out / f"{name}.ext").unlink()
        (out / f"{name}.key").chmod(0o600)
    (out / "ca.srl").unlink(missing_ok=True)
    (out / "ca.key").chmod(0o600)
    return out


def _files(certs: Path, name: str) -> tuple[str, str, str]:
    certs = Path(certs).resolve()
    paths = certs / "ca.pem", certs / f"{name}.pem", certs / f"{name}.key"
    for p in paths:
        if not p.is_file():
            raise CredentialsError(f"{p}: missing (make the run's credentials with: etar-bench certs {certs})")
    return tuple(str(p) for p in paths)


def router_options(certs, run_id: str, listen: str, roles=ROLES) -> ZenohOptions:
    """The runner's session: a router on ``listen`` (tls/HOST:PORT) that takes mutual
    TLS only and lets the run's roles, and nobody else, use etar/<run_id>/**."""
    ca, cert, key = _files(certs, "router")
    acl = {"enabled": True, "default_permission": "deny",
           "rules": [{"id": "run", "permission": "allow", "flows": ["ingress", "egress"],
                      "key_exprs": [topics.prefix(run_id) + "/**"], "messages": MESSAGES}],
           "subjects": [{"id": "roles", "cert_common_names": list(roles)}],
           "policies": [{"rules": ["run"], "subjects": ["roles"]}]}
    tls = {"root_ca_certificate": ca, "enable_mtls": True, "listen_certificate": cert, "listen_private_key": key}
    return ZenohOptions(mode="router", connect=(), listen=(listen,),
                        cfg=(("transport/link/protocols", json.dumps(["tls"])),
                             ("transport/link/tls", json.dumps(tls)), ("access_control", json.dumps(acl))))


def client_options(certs, role: str, connect: str) -> ZenohOptions:
    """A service's session: a client of the run's router with its role's certificate."""
    ca, cert, key = _files(certs, role)
    tls = {"root_ca_certificate": ca, "enable_mtls": True, "connect_certificate": cert, "connect_private_key": key}
    return ZenohOptions(mode="client", connect=(connect,), listen=(),
                        cfg=(("transport/link/tls", json.dumps(tls)),))
