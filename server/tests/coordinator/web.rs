//! The web front on the HTTP listener: the page's static files with their content policy, the
//! proto JSON calls (`POST /stylenerf.v1.JobService/<Method>`) with Connect-style errors and
//! the same tenancy as gRPC, and browser uploads (`POST /upload`) with the optional checksum.

use serde_json::{json, Value};
use stylenerf_server::proto::v1 as pb;
use stylenerf_testkit::*;

struct Web {
    base: String,
    http: reqwest::Client,
}

impl Web {
    async fn call(&self, token: Option<&str>, method: &str, body: Value) -> (u16, Value) {
        let mut request = self
            .http
            .post(format!("{}/stylenerf.v1.JobService/{method}", self.base))
            .header("content-type", "application/json")
            .body(body.to_string());
        if let Some(token) = token {
            request = request.bearer_auth(token);
        }
        let response = request.send().await.unwrap();
        let status = response.status().as_u16();
        (
            status,
            serde_json::from_str(&response.text().await.unwrap()).unwrap(),
        )
    }

    async fn upload(
        &self,
        token: &str,
        query: &str,
        data: &[u8],
        sha: Option<&str>,
    ) -> (u16, Value) {
        let mut request = self
            .http
            .post(format!("{}/upload?{query}", self.base))
            .bearer_auth(token)
            .body(data.to_vec());
        if let Some(sha) = sha {
            request = request.header("x-content-sha256", sha);
        }
        let response = request.send().await.unwrap();
        let status = response.status().as_u16();
        (
            status,
            serde_json::from_str(&response.text().await.unwrap()).unwrap(),
        )
    }
}

fn fields(error: &Value) -> Vec<String> {
    error["violations"]
        .as_array()
        .map(|v| {
            v.iter()
                .map(|v| v["field"].as_str().unwrap().to_string())
                .collect()
        })
        .unwrap_or_default()
}

#[tokio::test]
async fn the_page_and_its_json_api_work_like_the_grpc_api() {
    let dir = tempfile::tempdir().unwrap();
    let mut with_http = config(dir.path());
    with_http.http_listen = Some("127.0.0.1:0".parse().unwrap());
    let server = start(with_http).await;
    let mut alice = jobs_client(&server, Some(ALICE)).await;
    // The HTTP listener's address, as the coordinator signs it into artifact URLs.
    let job = create_job(&mut alice).await;
    let url = alice
        .get_artifact_url(pb::GetArtifactUrlRequest {
            job_id: job.id.clone(),
            key: job.dataset_key.clone(),
            ttl_seconds: 0,
        })
        .await
        .unwrap()
        .into_inner()
        .url;
    let base = url.split("/v1/").next().unwrap().to_string();
    let web = Web {
        base,
        http: reqwest::Client::new(),
    };

    // The page: static, same-origin only.
    let page = web.http.get(format!("{}/", web.base)).send().await.unwrap();
    assert_eq!(page.status().as_u16(), 200);
    let policy = page.headers()["content-security-policy"]
        .to_str()
        .unwrap()
        .to_string();
    assert!(policy.contains("default-src 'self'"), "{policy}");
    assert!(page.text().await.unwrap().contains("/app.js"));
    let script = web
        .http
        .get(format!("{}/app.js", web.base))
        .send()
        .await
        .unwrap();
    assert!(script.text().await.unwrap().contains("JobService"));

    // No token, a bad token: Connect's unauthenticated.
    let (status, error) = web.call(None, "ListJobs", json!({})).await;
    assert_eq!(
        (status, error["code"].as_str()),
        (401, Some("unauthenticated"))
    );
    let (status, _) = web
        .call(Some("not-a-token-at-all"), "ListJobs", json!({}))
        .await;
    assert_eq!(status, 401);

    // Browser uploads: the checksum is checked when sent, the content always.
    let style = png(8, 8);
    let (status, receipt) = web
        .upload(
            ALICE,
            "kind=STYLE_IMAGE&filename=wave.png",
            &style,
            Some(&sha256(&style)),
        )
        .await;
    assert_eq!(status, 200, "{receipt}");
    let style_id = receipt["upload_id"].as_str().unwrap().to_string();
    let (status, error) = web
        .upload(
            ALICE,
            "kind=STYLE_IMAGE&filename=wave.png",
            &style,
            Some(&sha256(b"x")),
        )
        .await;
    assert_eq!(
        (status, fields(&error)),
        (400, vec!["x-content-sha256".to_string()])
    );
    let (status, error) = web
        .upload(ALICE, "kind=PICTURE&filename=wave.png", &style, None)
        .await;
    assert_eq!((status, fields(&error)), (400, vec!["kind".to_string()]));
    let (status, error) = web
        .upload(ALICE, "kind=STYLE_IMAGE&filename=../wave.png", &style, None)
        .await;
    assert_eq!(
        (status, fields(&error)),
        (400, vec!["filename".to_string()])
    );
    let (status, error) = web
        .upload(ALICE, "kind=STYLE_IMAGE&filename=e.png", b"", None)
        .await;
    assert_eq!((status, fields(&error)), (400, vec!["body".to_string()]));
    let (status, error) = web
        .upload(
            ALICE,
            "kind=STYLE_IMAGE&filename=x.png",
            b"not an image",
            None,
        )
        .await;
    assert_eq!((status, fields(&error)), (400, vec!["data".to_string()]));
    let (status, receipt) = web
        .upload(
            ALICE,
            "kind=DATASET_ARCHIVE&filename=lego.tar",
            &scene_tar(),
            None,
        )
        .await;
    assert_eq!(status, 200, "{receipt}");
    assert!(receipt["summary"].as_str().unwrap().contains("2 frames"));
    let scene_id = receipt["upload_id"].as_str().unwrap().to_string();

    // A job created, read and listed in proto JSON.
    let request = json!({
        "name": "from the page",
        "preset": "tiny",
        "dataset": {"upload_id": scene_id},
        "styles": [{"upload_id": style_id}],
    });
    let (status, created) = web.call(Some(ALICE), "CreateJob", request.clone()).await;
    assert_eq!(status, 200, "{created}");
    let id = created["job"]["id"].as_str().unwrap().to_string();
    assert_eq!(
        created["job"]["tasks"].as_array().unwrap().len(),
        Source::Dataset.stages().len()
    );
    assert_eq!(created["job"]["state"], "JOB_STATE_QUEUED");
    let (status, listed) = web.call(Some(ALICE), "ListJobs", json!({})).await;
    assert_eq!(status, 200);
    assert_eq!(listed["jobs"].as_array().unwrap().len(), 2);
    let (status, events) = web
        .call(Some(ALICE), "ListEvents", json!({"job_id": id}))
        .await;
    assert_eq!(status, 200);
    assert!(!events["events"].as_array().unwrap().is_empty(), "{events}");

    // Invalid requests name their fields; another owner sees nothing.
    let mut bad = request.clone();
    bad["preset"] = json!("nope");
    let (status, error) = web.call(Some(ALICE), "CreateJob", bad).await;
    assert_eq!((status, fields(&error)), (400, vec!["preset".to_string()]));
    let (status, error) = web.call(Some(ALICE), "GetJob", json!({"job_id": 7})).await;
    assert_eq!((status, fields(&error)), (400, vec!["body".to_string()]));
    let (status, error) = web.call(Some(BOB), "GetJob", json!({"job_id": id})).await;
    assert_eq!((status, error["code"].as_str()), (404, Some("not_found")));
    let (status, error) = web
        .call(Some(BOB), "ListEvents", json!({"job_id": id}))
        .await;
    assert_eq!((status, error["code"].as_str()), (404, Some("not_found")));
    let (_, listed) = web.call(Some(BOB), "ListJobs", json!({})).await;
    assert!(
        listed["jobs"].as_array().is_none_or(Vec::is_empty),
        "{listed}"
    );
    let (status, error) = web.call(Some(WORKER), "ListJobs", json!({})).await;
    assert_eq!(
        (status, error["code"].as_str()),
        (403, Some("permission_denied"))
    );
    let (status, error) = web.call(Some(ALICE), "Teleport", json!({})).await;
    assert_eq!(
        (status, error["code"].as_str()),
        (404, Some("unimplemented"))
    );

    let (status, cancelled) = web
        .call(Some(ALICE), "CancelJob", json!({"job_id": id}))
        .await;
    assert_eq!(
        (status, cancelled["state"].as_str()),
        (200, Some("JOB_STATE_CANCELLED"))
    );
    server.shutdown().await.unwrap();
}
