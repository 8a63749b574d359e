"""Certificates for tests, made with `cryptography`: a CA and the leaf certificates it signs (the
Zenoh mTLS tests, the OPC UA server's)."""

from __future__ import annotations

import datetime
import ipaddress
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec, rsa
from cryptography.x509.oid import NameOID


class Pki:
    """A CA and leaf certificates (EC P-256, or RSA 2048 with ``rsa``: what OPC UA's Basic256Sha256
    needs) written as PEM files; keys chmod 600."""

    def __init__(self, root: Path, ca_cn: str = "cell-ca", *, rsa: bool = False) -> None:
        self.root = root
        self.rsa = rsa
        root.mkdir(parents=True, exist_ok=True)
        self.now = datetime.datetime.now(datetime.UTC)
        self.ca_key = self._key()
        self.ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, ca_cn)])
        ca = self._builder(self.ca_name, self.ca_key.public_key()).add_extension(
            x509.BasicConstraints(ca=True, path_length=None), critical=True
        )
        self.ca_file = self._write_cert(ca.sign(self.ca_key, hashes.SHA256()), "ca.pem")

    def _builder(self, subject: x509.Name, public_key) -> x509.CertificateBuilder:
        return (
            x509.CertificateBuilder()
            .subject_name(subject)
            .issuer_name(self.ca_name)
            .public_key(public_key)
            .serial_number(x509.random_serial_number())
            .not_valid_before(self.now - datetime.timedelta(hours=1))
            .not_valid_after(self.now + datetime.timedelta(days=1))
        )

    def _write_cert(self, cert: x509.Certificate, name: str) -> Path:
        path = self.root / name
        path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
        return path

    def _key(self):
        return rsa.generate_private_key(65537, 2048) if self.rsa else ec.generate_private_key(ec.SECP256R1())

    def leaf(self, cn: str, *, uri: str | None = None) -> tuple[Path, Path]:
        """A certificate for ``cn`` (localhost, 127.0.0.1; ``uri``: an OPC UA application URI too)."""
        key = self._key()
        names: list[x509.GeneralName] = [
            x509.DNSName("localhost"),
            x509.IPAddress(ipaddress.ip_address("127.0.0.1")),
        ]
        if uri is not None:
            names.append(x509.UniformResourceIdentifier(uri))
        san = x509.SubjectAlternativeName(names)
        cert = self._builder(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)]), key.public_key())
        cert_file = self._write_cert(
            cert.add_extension(san, critical=False).sign(self.ca_key, hashes.SHA256()), f"{cn}.pem"
        )
        key_file = self.root / f"{cn}.key"
        key_file.write_bytes(
            key.private_bytes(
                serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
            )
        )
        key_file.chmod(0o600)
        return cert_file, key_file
