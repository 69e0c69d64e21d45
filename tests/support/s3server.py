"""An S3-compatible server on the loopback for the records upload tests.

It is moto's standalone server (``moto_server``, a development dependency): an
S3-compatible HTTP service, not AWS; nothing leaves the machine. It runs with request
authentication on (``INITIAL_NO_AUTH_ACTION_COUNT``): the first few requests, which
create the bucket, an IAM user and that user's access key with boto3, go through
unauthenticated; every request after that must carry a valid Signature Version 4 of a
known access key, so a wrong key or a bad signature is refused as a real bucket refuses
it. boto3 is also the independent reader the tests check the uploaded objects with.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import boto3

from roost_api.ports import free_port
from roost_operator.records.s3 import Credentials
from tests.support.waiting import wait_until

MOTO_SERVER = Path(sys.executable).parent / "moto_server"
REGION = "eu-central-1"
SETUP_REQUESTS = 4
"""Requests let through unauthenticated: the bucket, the user, its policy, its key."""
POLICY = {
    "Version": "2012-10-17",
    "Statement": [{"Effect": "Allow", "Action": "s3:*", "Resource": "*"}],
}


@dataclass(frozen=True)
class S3Server:
    endpoint: str
    bucket: str
    credentials: Credentials

    def client(self) -> Any:
        """A boto3 S3 client with the user's key (the independent reader)."""
        return boto3.client(
            "s3",
            endpoint_url=self.endpoint,
            region_name=REGION,
            aws_access_key_id=self.credentials.access_key_id,
            aws_secret_access_key=self.credentials.secret_access_key,
        )

    def objects(self) -> dict[str, bytes]:
        """Every object in the bucket: key -> bytes."""
        client = self.client()
        listed = client.list_objects_v2(Bucket=self.bucket).get("Contents", [])
        return {
            o["Key"]: client.get_object(Bucket=self.bucket, Key=o["Key"])["Body"].read()
            for o in listed
        }

    def write_credentials(self, directory: Path, credentials: Credentials | None = None) -> Path:
        """The files a mounted Secret would give the operator."""
        use = credentials or self.credentials
        directory.mkdir(parents=True, exist_ok=True)
        (directory / "accessKeyId").write_text(use.access_key_id + "\n")
        (directory / "secretAccessKey").write_text(use.secret_access_key + "\n")
        return directory


@contextmanager
def s3_server(log: Path, bucket: str = "flights") -> Iterator[S3Server]:
    """Start the server on 127.0.0.1, create ``bucket`` and a user allowed to use it."""
    port = free_port()
    endpoint = f"http://127.0.0.1:{port}"
    env = {
        **os.environ,
        "INITIAL_NO_AUTH_ACTION_COUNT": str(SETUP_REQUESTS),
        # Placeholders for boto3 during setup (unauthenticated then); never sent anywhere
        # but this server.
        "AWS_ACCESS_KEY_ID": "setup",
        "AWS_SECRET_ACCESS_KEY": "setup",
    }
    with log.open("wb") as output:
        process = subprocess.Popen(
            [str(MOTO_SERVER), "-H", "127.0.0.1", "-p", str(port)],
            stdout=output,
            stderr=subprocess.STDOUT,
            env=env,
        )
    try:
        setup = boto3.session.Session(
            aws_access_key_id="setup", aws_secret_access_key="setup", region_name=REGION
        )
        iam = setup.client("iam", endpoint_url=endpoint)
        wait_until("the S3-compatible server listening", lambda: _listening(port), 60, 0.1)
        setup.client("s3", endpoint_url=endpoint).create_bucket(
            Bucket=bucket, CreateBucketConfiguration={"LocationConstraint": REGION}
        )
        iam.create_user(UserName="roost")
        iam.put_user_policy(
            UserName="roost", PolicyName="bundles", PolicyDocument=json.dumps(POLICY)
        )
        key = iam.create_access_key(UserName="roost")["AccessKey"]
        yield S3Server(endpoint, bucket, Credentials(key["AccessKeyId"], key["SecretAccessKey"]))
    finally:
        process.terminate()
        process.wait(timeout=30)


def _listening(port: int) -> bool:
    try:
        socket.create_connection(("127.0.0.1", port), timeout=1).close()
    except OSError:
        return False
    return True
