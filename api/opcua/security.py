"""Who may do what on the OPC UA server: users with the REST roles, a permission ruleset, the certificate.

- :class:`Users` checks a username/password against the scrypt hashes
  (:mod:`api.opcua.passwords`); anonymous sessions and unknown users are
  refused at ActivateSession, so they can read nothing.
- :class:`RoleRuleset` decides per request type: every user browses, reads,
  subscribes and sends Call requests; nobody writes attributes or changes the
  address space: the loops change only through the methods. asyncua's own
  roles (Admin, User) cannot say that, hence a ruleset of our own. The loops'
  methods (Tune, Break, Apply, AutoTuningOn/Off) check the operator role
  themselves (:func:`may_call`), so a viewer's call is refused with a status
  and a message per method, as REST's 403 has a body.
- :class:`TrustedClients` (config ``trusted_clients``, a folder of trusted
  client certificates) refuses a session whose client certificate is not
  trusted: at CreateSession (asyncua's certificate validator over its
  TrustStore, reloaded per session) and again at ActivateSession on the
  secure channel's own certificate (:class:`Users`), which the client has
  proved it holds the key of.
- Refusals are expected outcomes, not errors: each is logged once at
  WARNING in ``autotuner.api.opcua`` with who, what and why (a viewer's
  Tune names the loop and the method), and :class:`QuietRefusals` keeps
  asyncua's own ERROR lines for them out of the log.
- :func:`ensure_certificate` makes the server's self-signed application
  certificate and key on first start (for Basic256Sha256) and reuses them after.
"""

from __future__ import annotations

import contextvars
import logging
import os
import socket
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from asyncua import ua
from asyncua.common.utils import Buffer, ServiceError
from asyncua.crypto import cert_gen
from asyncua.crypto.permission_rules import PermissionRuleset, User, UserRole
from asyncua.crypto.truststore import TrustStore
from asyncua.crypto.validator import CertificateValidator, CertificateValidatorOptions
from cryptography import x509
from cryptography.hazmat.primitives import hashes
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from api.auth import RANKS
from autotuner.service.config import OpcUaUser, Role

from .passwords import verify_password

log = logging.getLogger("autotuner.api.opcua")

# Request types every activated user may send: session housekeeping, browse, read, subscriptions.
_READ_TYPES = (
    "CreateSessionRequest", "CloseSessionRequest", "ActivateSessionRequest", "ReadRequest", "BrowseRequest",
    "BrowseNextRequest", "GetEndpointsRequest", "FindServersRequest", "TranslateBrowsePathsToNodeIdsRequest",
    "CreateSubscriptionRequest", "ModifySubscriptionRequest", "DeleteSubscriptionsRequest",
    "TransferSubscriptionsRequest", "CreateMonitoredItemsRequest", "ModifyMonitoredItemsRequest",
    "DeleteMonitoredItemsRequest", "PublishRequest", "RepublishRequest", "CloseSecureChannelRequest",
    "SetMonitoringModeRequest", "SetPublishingModeRequest", "RegisterNodesRequest", "UnregisterNodesRequest",
)
READ_REQUESTS = frozenset(ua.NodeId(getattr(ua.ObjectIds, f"{name}_Encoding_DefaultBinary")) for name in _READ_TYPES)
CALL_REQUEST = ua.NodeId(ua.ObjectIds.CallRequest_Encoding_DefaultBinary)
WRITE_REQUEST = ua.NodeId(ua.ObjectIds.WriteRequest_Encoding_DefaultBinary)
# Why a request is refused to an activated user: a loop's method needs the operator; nothing is written.
NEEDS_OPERATOR = "forbidden: this needs the operator role"
READ_ONLY = "forbidden: the variables are read-only (the loops change only through the methods)"

# The user of the request being processed. asyncua handles one connection's requests in one task, one after
# the other, and asks the ruleset right before running each; the methods read it to know who called.
CALLER: contextvars.ContextVar[RoledUser | None] = contextvars.ContextVar("opcua_caller", default=None)


@dataclass
class RoledUser(User):
    """An asyncua user with the REST role (viewer, operator, admin) of its config entry."""

    api_role: Role = "viewer"


def describe(cert: x509.Certificate) -> str:
    """A client certificate as an administrator finds it again: its CN, application URI and SHA-1 thumbprint
    (what UaExpert and most clients show)."""
    names = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    try:
        uris = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value \
            .get_values_for_type(x509.UniformResourceIdentifier)
    except x509.ExtensionNotFound:
        uris = []
    return (f"CN={names[0].value if names else '?'}, URI={uris[0] if uris else '?'}, "
            f"SHA-1 {cert.fingerprint(hashes.SHA1()).hex()}")  # noqa: S303 - a thumbprint, not a signature


class TrustedClients:
    """The client certificates trusted by the server: the certificates in ``folder`` (DER or PEM), and every
    certificate signed by a CA certificate there; asyncua's :class:`TrustStore`, without revocation lists.

    Called by asyncua at CreateSession (``Server.set_certificate_validator``) with the client's certificate:
    it must be within its validity period, name the client's application URI and be trusted, else the
    session is refused (``BadCertificateUntrusted``, …) and logged at WARNING. The folder is read again for
    every new session, so a certificate copied in is trusted from the next connection, without a restart.
    """

    OPTIONS = (CertificateValidatorOptions.TIME_RANGE | CertificateValidatorOptions.URI
               | CertificateValidatorOptions.TRUSTED | CertificateValidatorOptions.PEER_CLIENT)

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.store = TrustStore([folder], [])
        self._validator = CertificateValidator(self.OPTIONS, self.store)

    async def load(self) -> None:
        """Read the folder (at start: an unreadable folder fails the start)."""
        await self.store.load_trust()

    async def __call__(self, cert: x509.Certificate, client: ua.ApplicationDescription) -> None:
        await self.load()
        try:
            await self._validator.validate(cert, client)
        except ServiceError as exc:
            log.warning("OPC UA: client certificate %s of %s refused: %s (trusted certificates: %s)", describe(cert),
                        client.ApplicationUri, ua.StatusCode(exc.code).name, self.folder)
            raise

    def trusts(self, der: bytes | None) -> bool:
        """Whether the certificate ``der`` (None: the channel has none) is trusted, as loaded last."""
        return der is not None and self.store.validate(x509.load_der_x509_certificate(der))


class Users:
    """The user manager asyncua asks at ActivateSession: a known name with its password, or None (refused).

    With ``trusted`` the secure channel's client certificate must be trusted too: CreateSession checked the
    certificate the client named, this checks the one whose key signed the channel (they could differ).
    """

    def __init__(self, users: list[OpcUaUser], trusted: TrustedClients | None = None) -> None:
        self._users = {user.name: user for user in users}
        self._trusted = trusted

    def __len__(self) -> int:
        return len(self._users)

    def get_user(self, iserver: Any, username: str | None = None, password: str | None = None,
                 certificate: Any = None) -> RoledUser | None:
        """The user ``username`` if ``password`` matches its hash; None (BadUserAccessDenied) otherwise."""
        entry = self._users.get(username or "")
        if entry is None or password is None or not verify_password(password, entry.password_hash):
            log.warning("OPC UA: login of %r refused: unknown user or wrong password", username)
            return None
        if self._trusted is not None and not self._trusted.trusts(certificate):
            log.warning("OPC UA: login of %r refused: the secure channel's client certificate is not trusted "
                        "(trusted certificates: %s)", username, self._trusted.folder)
            return None
        return RoledUser(role=UserRole.User, name=entry.name, api_role=entry.role)


def may_call(user: Any) -> bool:
    """Whether ``user`` holds the operator role (needed for every method of the loops)."""
    return isinstance(user, RoledUser) and RANKS[user.api_role] >= RANKS["operator"]


class RoleRuleset(PermissionRuleset):
    """Everyone activated reads, subscribes and calls (the loops' methods refuse viewers); writes and node
    management are refused to all."""

    def check_validity(self, user: Any, action_type_id: ua.NodeId, body: Any) -> bool:
        if not isinstance(user, RoledUser):
            return False  # anonymous, or a session not activated by :class:`Users`
        CALLER.set(user)
        if action_type_id in READ_REQUESTS or action_type_id == CALL_REQUEST:  # the methods check the role
            return True
        _log_refusal(user, action_type_id, body)
        return False


def _targets(body: Buffer, parameters: type, items: str) -> list[ua.NodeId]:
    """The NodeIds a Write's body names (``parameters``: its parameter struct, ``items`` its list)."""
    from asyncua.ua.ua_binary import struct_from_binary

    try:  # a copy: asyncua decodes the body itself after the ruleset
        return [item.NodeId for item in getattr(struct_from_binary(parameters, body.copy()), items)]
    except Exception:  # a body asyncua cannot decode either: the refusal is logged without its targets
        return []


def _log_refusal(user: RoledUser, action_type_id: ua.NodeId, body: Buffer) -> None:
    """One WARNING line per refused request: who, what (the nodes of a Write), why."""
    who = f"opcua:{user.name} ({user.api_role})"
    if action_type_id == WRITE_REQUEST:
        nodes = ", ".join(str(n.Identifier) for n in _targets(body, ua.WriteParameters, "NodesToWrite"))
        log.warning("OPC UA: write of %s by %s refused: %s", nodes or "?", who, READ_ONLY)
        return
    request = ua.ObjectIdNames.get(action_type_id.Identifier, str(action_type_id))
    request = request.removesuffix("_Encoding_DefaultBinary")
    log.warning("OPC UA: %s by %s refused: %s", request, who, READ_ONLY)


class QuietRefusals(logging.Filter):
    """On asyncua's server loggers: drops its ERROR lines for refusals that are expected outcomes and logged
    already (each refusal of :class:`RoleRuleset`, :class:`Users` and :class:`TrustedClients` at WARNING, a
    request without a session by asyncua itself at WARNING); an anonymous login's ERROR becomes our WARNING.
    Other errors pass unchanged."""

    FAULTS = frozenset({"BadUserAccessDenied", "BadIdentityTokenRejected", "BadCertificateUntrusted",
                        "BadCertificateTimeInvalid", "BadCertificateUriInvalid", "BadCertificateUseNotAllowed",
                        "BadCertificateInvalid"})
    # asyncua's TrustStore logs every untrusted certificate with a traceback, under a logger of its own.
    LOGGERS = ("asyncua.server.uaprocessor", "asyncua.server.internal_session", "asyncuagds.validate")

    def filter(self, record: logging.LogRecord) -> bool:
        message = str(record.msg)
        if message.startswith("sending service fault response") and record.args and record.args[-1] in self.FAULTS:
            return False
        if message.startswith("Not trusted certificate used"):  # TrustedClients logs the refusal
            return False
        if message.startswith("Rejected active session UserIdentityToken not supported"):
            log.warning("OPC UA: a login refused: only user name and password are accepted (no anonymous sessions)")
            return False
        return True


def state_dir(history: str) -> Path | None:
    """Where a generated certificate is kept: beside an SQLite history file; for a database URL in
    ``$AUTOTUNER_STATE_DIR`` or else the working directory; None for an in-memory history (the demo's): then
    it lives in a temporary folder as long as the server."""
    if history == ":memory:":
        return None
    if "://" not in history:
        return Path(history).resolve().parent
    return Path(os.environ.get("AUTOTUNER_STATE_DIR") or ".").resolve()


async def ensure_certificate(folder: Path, app_uri: str) -> tuple[Path, Path]:
    """The server's certificate (DER) and key (PEM) in ``folder``: made on first use (self-signed, RSA 2048,
    one year), reused after, made anew when invalid for ``app_uri`` or expired. The key is readable by the
    owner only."""
    folder.mkdir(parents=True, exist_ok=True)
    cert, key = folder / "opcua-server-cert.der", folder / "opcua-server-key.pem"
    if not key.is_file():  # made here, created owner-only: asyncua's own would be readable by others at first
        pem = cert_gen.dump_private_key_as_pem(cert_gen.generate_private_key())
        with os.fdopen(os.open(key, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600), "wb") as out:
            out.write(pem)
    await cert_gen.setup_self_signed_certificate(
        key, cert, app_uri, socket.gethostname(), [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH],
        {"organizationName": "relaytune", "commonName": "autotuner OPC UA server"})
    key.chmod(0o600)
    return cert, key
