"""A web backend as an integrator would write it, from proto/ and docs/API.md only.

Generates Python stubs from proto/ with grpcio-tools, then: uploads a scene archive and a
style image, creates a job with a webhook pointing at its own HTTP server, verifies every
delivery's Standard Webhooks signature with the job's secret, waits (on webhooks, not on a gRPC
stream) for the job to succeed, lists its artifacts, asks a signed URL for the animation and
downloads it with plain HTTP. Prints one JSON line with what it saw; exits non-zero on failure.

Usage: backend.py ENDPOINT TOKEN SCENE_TAR STYLE_PNG OUT_DIR   (tests/python_backend.rs runs it)
"""

import base64
import hashlib
import hmac
import http.server
import json
import os
import queue
import sys
import tempfile
import threading
import urllib.request

from grpc_tools import protoc

endpoint, token, scene_tar, style_png, out_dir = sys.argv[1:6]
root = os.path.join(os.path.dirname(__file__), "..", "..", "proto")
generated = tempfile.mkdtemp()
protos = ["stylenerf/v1/common.proto", "stylenerf/v1/jobs.proto"]
if protoc.main(["protoc", f"-I{root}", f"--python_out={generated}", f"--grpc_python_out={generated}", *protos]) != 0:
    sys.exit("protoc failed")
sys.path.insert(0, generated)

import grpc  # noqa: E402
from google.protobuf import json_format  # noqa: E402
from stylenerf.v1 import common_pb2, jobs_pb2, jobs_pb2_grpc  # noqa: E402

# The webhook receiver: every delivery goes to a queue after its signature is checked.
deliveries = queue.Queue()
secret_box = {}


class Hook(http.server.BaseHTTPRequestHandler):
    def do_POST(self):
        body = self.rfile.read(int(self.headers["content-length"]))
        msg_id = self.headers["webhook-id"]
        timestamp = self.headers["webhook-timestamp"]
        key = base64.b64decode(secret_box["secret"].removeprefix("whsec_"))
        expected = base64.b64encode(
            hmac.new(key, f"{msg_id}.{timestamp}.".encode() + body, hashlib.sha256).digest()
        ).decode()
        signatures = [s.split(",", 1)[1] for s in self.headers["webhook-signature"].split()]
        ok = any(hmac.compare_digest(expected, s) for s in signatures)
        self.send_response(204 if ok else 401)
        self.end_headers()
        deliveries.put((ok, json.loads(body)))

    def log_message(self, *args):
        pass


server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Hook)
threading.Thread(target=server.serve_forever, daemon=True).start()
hook_url = f"http://127.0.0.1:{server.server_address[1]}/stylenerf"

channel = grpc.insecure_channel(endpoint.removeprefix("http://"))
jobs = jobs_pb2_grpc.JobServiceStub(channel)
auth = [("authorization", f"Bearer {token}")]


def upload(kind, path):
    data = open(path, "rb").read()
    header = jobs_pb2.UploadHeader(
        kind=kind,
        filename=os.path.basename(path),
        total_size=len(data),
        sha256=hashlib.sha256(data).hexdigest(),
    )

    def chunks():
        yield jobs_pb2.UploadChunk(header=header)
        for i in range(0, len(data), 1 << 20):
            yield jobs_pb2.UploadChunk(data=data[i : i + (1 << 20)])

    return jobs.Upload(chunks(), metadata=auth).upload_id


scene = upload(jobs_pb2.UPLOAD_KIND_DATASET_ARCHIVE, scene_tar)
style = upload(jobs_pb2.UPLOAD_KIND_STYLE_IMAGE, style_png)
created = jobs.CreateJob(
    jobs_pb2.CreateJobRequest(
        name="python-backend",
        dataset=jobs_pb2.InputRef(upload_id=scene),
        styles=[jobs_pb2.InputRef(upload_id=style)],
        preset="tiny",
        webhook=jobs_pb2.Webhook(url=hook_url, events=[jobs_pb2.EVENT_KIND_JOB_STATE]),
    ),
    metadata=auth,
)
secret_box["secret"] = created.webhook_secret
job_id = created.job.id

# Wait for the job's end, learning of it only through webhooks.
states = []
while True:
    ok, event = deliveries.get(timeout=600)
    if not ok:
        sys.exit(f"a delivery's signature did not verify: {event}")
    parsed = json_format.ParseDict(event, jobs_pb2.Event())
    if parsed.job_id != job_id:
        sys.exit(f"a delivery for another job: {event}")
    states.append(common_pb2.JobState.Name(parsed.job_state))
    if parsed.job_state in (common_pb2.JOB_STATE_SUCCEEDED, common_pb2.JOB_STATE_FAILED, common_pb2.JOB_STATE_CANCELLED):
        break
if states[-1] != "JOB_STATE_SUCCEEDED":
    sys.exit(f"the job ended {states}")

artifacts = jobs.ListArtifacts(jobs_pb2.ListArtifactsRequest(job_id=job_id), metadata=auth).artifacts
animation = next(a for a in artifacts if a.key.endswith("animation.gif"))
link = jobs.GetArtifactUrl(
    jobs_pb2.GetArtifactUrlRequest(job_id=job_id, key=animation.key, ttl_seconds=300),
    metadata=auth,
)
with urllib.request.urlopen(link.url) as response:  # plain HTTP, no token
    content_type = response.headers["content-type"]
    data = response.read()
path = os.path.join(out_dir, "animation.gif")
with open(path, "wb") as f:
    f.write(data)
print(
    json.dumps(
        {
            "job_id": job_id,
            "states": states,
            "key": animation.key,
            "url": link.url,
            "content_type": content_type,
            "bytes": len(data),
            "sha256_matches": hashlib.sha256(data).hexdigest() == animation.sha256,
            "gif": data[:6] in (b"GIF87a", b"GIF89a"),
            "path": path,
        }
    )
)
