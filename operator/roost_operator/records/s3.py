"""A small S3-compatible client: signed HEAD and PUT of one object, nothing else.

The operator copies each finished Mission bundle to a bucket when one is configured
(:mod:`roost_operator.records.upload`). That needs two requests — "is this object there
with this SHA-256?" and "store these bytes" — so instead of an SDK (tens of MB in the
operator image for two calls) this module signs them itself with AWS Signature Version 4
over urllib3, which the operator already uses. Path-style addressing
(``<endpoint>/<bucket>/<key>``) works with AWS S3, MinIO, Ceph RGW, Garage and the other
S3-compatible servers.

Each object carries its SHA-256 twice: as ``x-amz-content-sha256`` (the signed payload
hash: the server refuses bytes that do not match it) and as the user metadata
``x-amz-meta-sha256``, which a HEAD returns, so an object already in the bucket with the
same content is skipped: an upload cut half way resumes with the objects still missing.

Failures are sorted into two kinds, because the caller treats them differently:
:class:`BucketError` with ``permanent=True`` (bad credentials, no such bucket, wrong
region, access denied: trying again changes nothing, so it is reported once) and
``permanent=False`` (unreachable, timeouts, 5xx, throttling: tried again with backoff).
"""

from __future__ import annotations

import hashlib
import hmac
import re
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from urllib.parse import quote, urlsplit

import urllib3

EMPTY_SHA256 = hashlib.sha256(b"").hexdigest()
META_SHA256 = "x-amz-meta-sha256"
TEMPORARY_STATUS = frozenset({408, 429, 500, 502, 503, 504})
"""HTTP answers that say "not now" rather than "no"."""
TEMPORARY_CODES = frozenset({"RequestTimeout", "SlowDown", "InternalError", "ServiceUnavailable"})
"""S3 error codes that say "not now", whatever their HTTP status."""


@dataclass(frozen=True)
class Credentials:
    access_key_id: str
    secret_access_key: str
    session_token: str = ""

    @classmethod
    def from_directory(cls, directory: Path) -> Credentials:
        """The mounted Secret's files ``accessKeyId`` and ``secretAccessKey`` (and an
        optional ``sessionToken``), read at each upload so a rotated Secret is used
        without a restart. BucketError (permanent) when they are missing or empty."""
        try:
            key = (directory / "accessKeyId").read_text().strip()
            secret = (directory / "secretAccessKey").read_text().strip()
        except OSError as error:
            raise BucketError(
                f"the bucket's credentials cannot be read from {directory}: "
                f"{error.strerror or error} (is the Secret there, with both keys?)",
                permanent=True,
            ) from error
        token_file = directory / "sessionToken"
        token = token_file.read_text().strip() if token_file.is_file() else ""
        if not key or not secret:
            raise BucketError(f"the bucket's credentials in {directory} are empty", permanent=True)
        return cls(key, secret, token)


@dataclass(frozen=True)
class BucketSettings:
    """Where bundles are copied (``ROOST_RECORDS_S3_*``; chart ``operator.records.s3``)."""

    endpoint: str
    """``https://host[:port]`` of the S3-compatible service."""
    bucket: str
    region: str = "us-east-1"
    prefix: str = ""
    """Prepended to every key (``roost/`` puts bundles under ``roost/<bundle>/``)."""
    credentials_dir: Path = Path("/etc/roost/records-s3")

    def key(self, *parts: str) -> str:
        prefix = self.prefix.strip("/")
        return "/".join(p for p in (prefix, *parts) if p)

    def location(self, *parts: str) -> str:
        return f"s3://{self.bucket}/{self.key(*parts)}"


class BucketError(Exception):
    """The bucket did not take a request; ``permanent`` says whether trying again helps."""

    def __init__(self, message: str, *, permanent: bool) -> None:
        super().__init__(message)
        self.permanent = permanent


def signature_key(secret: str, day: str, region: str, service: str) -> bytes:
    key = ("AWS4" + secret).encode()
    for part in (day, region, service, "aws4_request"):
        key = hmac.new(key, part.encode(), hashlib.sha256).digest()
    return key


def sign(
    method: str,
    url: str,
    headers: Mapping[str, str],
    payload_sha256: str,
    *,
    credentials: Credentials,
    region: str,
    when: datetime,
    service: str = "s3",
) -> dict[str, str]:
    """``headers`` plus ``host``, ``x-amz-date``, ``x-amz-content-sha256`` and the
    ``Authorization`` of AWS Signature Version 4 (every header given is signed)."""
    parts = urlsplit(url)
    stamp = when.astimezone(UTC).strftime("%Y%m%dT%H%M%SZ")
    signed = {k.lower(): " ".join(str(v).split()) for k, v in headers.items()}
    signed["host"] = parts.netloc
    signed["x-amz-date"] = stamp
    signed["x-amz-content-sha256"] = payload_sha256
    if credentials.session_token:
        signed["x-amz-security-token"] = credentials.session_token
    names = sorted(signed)
    query = "&".join(
        sorted(
            f"{quote(k, safe='-_.~')}={quote(v, safe='-_.~')}"
            for k, _, v in (pair.partition("=") for pair in parts.query.split("&") if pair)
        )
    )
    canonical = "\n".join(
        [
            method,
            parts.path or "/",  # as sent: the caller encoded it once (Client.url)
            query,
            "".join(f"{name}:{signed[name]}\n" for name in names),
            ";".join(names),
            payload_sha256,
        ]
    )
    scope = f"{stamp[:8]}/{region}/{service}/aws4_request"
    to_sign = "\n".join(
        ["AWS4-HMAC-SHA256", stamp, scope, hashlib.sha256(canonical.encode()).hexdigest()]
    )
    key = signature_key(credentials.secret_access_key, stamp[:8], region, service)
    signature = hmac.new(key, to_sign.encode(), hashlib.sha256).hexdigest()
    signed["authorization"] = (
        f"AWS4-HMAC-SHA256 Credential={credentials.access_key_id}/{scope}, "
        f"SignedHeaders={';'.join(names)}, Signature={signature}"
    )
    return signed


class Client:
    """HEAD and PUT of objects in one bucket."""

    def __init__(
        self,
        settings: BucketSettings,
        credentials: Credentials,
        pool: urllib3.PoolManager,
        timeout: urllib3.Timeout | None = None,
    ) -> None:
        self.settings = settings
        self.credentials = credentials
        self.pool = pool
        self.timeout = timeout or urllib3.Timeout(connect=5.0, read=60.0)

    def url(self, key: str) -> str:
        base = self.settings.endpoint.rstrip("/")
        return f"{base}/{quote(self.settings.bucket, safe='')}/{quote(key, safe='/-_.~')}"

    def stored_sha256(self, key: str) -> str | None:
        """The ``sha256`` metadata of the object (None: no such object)."""
        response = self._request("HEAD", key, {}, EMPTY_SHA256, None)
        if response.status == 404:
            return None
        if not 200 <= response.status < 300:
            # A HEAD's answer has no body, so no error code: ask again with a GET of
            # one byte, whose refusal says why (InvalidAccessKeyId, NoSuchBucket, ...).
            response = self._request("GET", key, {"range": "bytes=0-0"}, EMPTY_SHA256, None)
        self._check(response, "HEAD", key)
        return response.headers.get(META_SHA256)

    def put_file(self, key: str, path: Path, sha256: str, content_type: str) -> None:
        """Store ``path``'s bytes under ``key``; the server checks them against ``sha256``."""
        size = path.stat().st_size
        headers = {
            "content-length": str(size),
            "content-type": content_type,
            META_SHA256: sha256,
        }
        with path.open("rb") as body:
            response = self._request("PUT", key, headers, sha256, body)
        self._check(response, "PUT", key)

    def _request(
        self,
        method: str,
        key: str,
        headers: Mapping[str, str],
        payload_sha256: str,
        body: object,
    ) -> urllib3.BaseHTTPResponse:
        url = self.url(key)
        signed = sign(
            method,
            url,
            headers,
            payload_sha256,
            credentials=self.credentials,
            region=self.settings.region,
            when=datetime.now(UTC),
        )
        try:
            return self.pool.request(
                method,
                url,
                body=body,  # type: ignore[arg-type]
                headers=signed,
                timeout=self.timeout,
                retries=False,
                redirect=False,
            )
        except (urllib3.exceptions.HTTPError, OSError) as error:
            raise BucketError(
                f"{self.settings.endpoint} unreachable ({type(error).__name__}: {error})",
                permanent=False,
            ) from error

    def _check(self, response: urllib3.BaseHTTPResponse, method: str, key: str) -> None:
        if 200 <= response.status < 300:
            return
        code, message = error_of(response.data or b"")
        permanent = response.status not in TEMPORARY_STATUS and code not in TEMPORARY_CODES
        what = f"{code}: {message}" if code else _status_meaning(response.status)
        raise BucketError(
            f"{method} s3://{self.settings.bucket}/{key}: HTTP {response.status} ({what})",
            permanent=permanent,
        )


def error_of(body: bytes) -> tuple[str, str]:
    """The ``<Code>`` and ``<Message>`` of an S3 error document ('' when absent)."""
    text = body[:4096].decode(errors="replace")
    code = re.search(r"<Code>([^<]*)</Code>", text)
    message = re.search(r"<Message>([^<]*)</Message>", text)
    return (code.group(1) if code else "", message.group(1) if message else "")


def _status_meaning(status: int) -> str:
    """What a bodiless answer (a HEAD's) most likely means."""
    return {
        301: "the bucket is in another region or at another endpoint",
        400: "a malformed request: is the region right?",
        403: "the credentials or the bucket's policy refuse access",
    }.get(status, "no error document")
