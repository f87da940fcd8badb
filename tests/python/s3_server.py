"""A local S3 endpoint for the object-storage tests (tests/src/s3/server.rs).

Starts moto's threaded server on 127.0.0.1 on a free port, prints one JSON line on
stdout ({"port": N} and, with --auth, the only valid credentials), then serves until its
stdin closes (the Rust harness holds the pipe; when the test process dies, so does this).

With --auth, moto checks every request's SigV4 signature against its IAM users: the
script creates one user with an access key and an s3:* policy, then turns checking on
(POST /moto-api/reset-auth with 0: no more unauthenticated actions allowed). The harness
turns it off around bucket creation, which it sends unsigned.

pip install -r tests/python/requirements.txt
"""

import json
import logging
import sys
import urllib.request


def speed_up_moto() -> None:
    """Two per-request costs of moto 5.2 that benchmarks would measure instead of the
    client (tests/benches/object_store.rs), taken out without changing what it answers:

    * every GET reads the object's whole value from its spooled temporary file, ranged
      GETs included (31 MB read for a 1 MB range of a nuScenes-sized drive): the value
      is kept as bytes once read, until the object is written again;
    * every request lists and stats moto's ~170 module directories to find its backend:
      the list is made once.
    """
    from moto import backends
    from moto.s3.models import FakeKey

    modules = tuple(backends.list_of_moto_modules())
    backends.list_of_moto_modules = lambda: modules

    value = FakeKey.value

    def cached(self):  # type: ignore[no-untyped-def]
        held = self.__dict__.get("_superflow_value")
        if held is None:
            held = value.fget(self)
            self.__dict__["_superflow_value"] = held
        return held

    def written(self, new_value):  # type: ignore[no-untyped-def]
        self.__dict__.pop("_superflow_value", None)
        value.fset(self, new_value)

    FakeKey.value = property(cached, written)


def main() -> int:
    auth = "--auth" in sys.argv[1:]
    try:
        from moto.server import ThreadedMotoServer
    except ImportError as e:
        print(
            f"moto is missing ({e}): pip install -r tests/python/requirements.txt",
            file=sys.stderr,
        )
        return 3
    speed_up_moto()

    # One log line per request would flood the test's stderr; errors still show.
    logging.getLogger("werkzeug").setLevel(logging.ERROR)
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    _, port = server.get_host_and_port()
    endpoint = f"http://127.0.0.1:{port}"
    ready = {"port": port}

    if auth:
        import boto3

        iam = boto3.client(
            "iam",
            endpoint_url=endpoint,
            region_name="us-east-1",
            aws_access_key_id="bootstrap",
            aws_secret_access_key="bootstrap",
        )
        iam.create_user(UserName="superflow")
        iam.put_user_policy(
            UserName="superflow",
            PolicyName="s3-all",
            PolicyDocument=json.dumps(
                {
                    "Version": "2012-10-17",
                    "Statement": [
                        {"Effect": "Allow", "Action": "s3:*", "Resource": "*"}
                    ],
                }
            ),
        )
        key = iam.create_access_key(UserName="superflow")["AccessKey"]
        request = urllib.request.Request(
            f"{endpoint}/moto-api/reset-auth",
            data=b"0",
            method="POST",
            headers={"Content-Type": "text/plain"},  # not a form: moto reads the raw body
        )
        urllib.request.urlopen(request).read()
        ready["access_key_id"] = key["AccessKeyId"]
        ready["secret_access_key"] = key["SecretAccessKey"]

    print(json.dumps(ready), flush=True)
    # The harness stops reading stdout after the ready line: nothing more may go there.
    sys.stdout = sys.stderr
    # Serve until the parent closes our stdin (or dies).
    sys.stdin.read()
    server.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
