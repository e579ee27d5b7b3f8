//! A client of `deocc serve`: connect, send a scene, read the progress and the result.

use std::time::Duration;

use deocc_geometry::PointCloud;
use deocc_pipeline::SceneInput;
use tonic::metadata::MetadataValue;
use tonic::transport::{Channel, Endpoint};
use tonic::{Request, Status};

use crate::proto::deocc_client::DeoccClient;
use crate::proto::{
    complete_event, CompleteRequest, CompleteResult, HealthRequest, HealthResponse,
};

/// A connection to a deocc server.
#[derive(Clone)]
pub struct Client {
    inner: DeoccClient<Channel>,
    token: Option<String>,
    max_message_bytes: usize,
}

/// What one `Complete` call returned.
pub struct Completion {
    pub result: CompleteResult,
    /// The stages reported, in order.
    pub stages: Vec<String>,
}

impl Completion {
    /// The completed cloud, decoded.
    pub fn cloud(&self) -> Result<PointCloud, crate::FieldError> {
        let msg = self
            .result
            .cloud
            .as_ref()
            .ok_or_else(|| crate::FieldError::new("cloud", "missing from the result"))?;
        crate::cloud2::decode(msg, "cloud")
    }
}

impl Client {
    /// Connects to `addr` (`http://127.0.0.1:50051`).
    pub async fn connect(
        addr: &str,
        token: Option<String>,
    ) -> Result<Self, tonic::transport::Error> {
        let channel = Endpoint::from_shared(addr.to_string())?
            .connect_timeout(Duration::from_secs(10))
            .connect()
            .await?;
        let max = 256 << 20;
        Ok(Self {
            inner: DeoccClient::new(channel)
                .max_decoding_message_size(max)
                .max_encoding_message_size(max),
            token,
            max_message_bytes: max,
        })
    }

    /// Longest timeout a call may ask for (a day).
    pub const MAX_TIMEOUT_S: u64 = 86_400;

    fn request<T>(&self, msg: T, timeout: Option<Duration>) -> Result<Request<T>, Status> {
        let mut r = Request::new(msg);
        if let Some(t) = timeout {
            // gRPC's timeout header holds at most 8 digits of its unit: beyond a day, tonic's
            // encoding of it panicked.
            if t.is_zero() || t > Duration::from_secs(Self::MAX_TIMEOUT_S) {
                return Err(Status::invalid_argument(format!(
                    "timeout {t:?} must be above zero and at most {} s",
                    Self::MAX_TIMEOUT_S
                )));
            }
            r.set_timeout(t);
        }
        if let Some(token) = &self.token {
            let v: MetadataValue<_> = format!("Bearer {token}")
                .parse()
                .map_err(|_| Status::invalid_argument("the token is not a valid header value"))?;
            r.metadata_mut().insert("authorization", v);
        }
        Ok(r)
    }

    /// The largest message this client sends or accepts.
    pub fn max_message_bytes(&self) -> usize {
        self.max_message_bytes
    }

    pub async fn health(&mut self) -> Result<HealthResponse, Status> {
        let r = self.request(HealthRequest {}, Some(Duration::from_secs(10)))?;
        Ok(self.inner.health(r).await?.into_inner())
    }

    /// Sends `req` and reads its events to the end.
    pub async fn complete(
        &mut self,
        req: CompleteRequest,
        timeout: Option<Duration>,
    ) -> Result<Completion, Status> {
        let r = self.request(req, timeout)?;
        let mut stream = self.inner.complete(r).await?.into_inner();
        let mut stages = Vec::new();
        while let Some(event) = stream.message().await? {
            match event.event {
                Some(complete_event::Event::Progress(p)) => stages.push(p.stage),
                Some(complete_event::Event::Result(result)) => {
                    return Ok(Completion { result, stages })
                }
                None => {}
            }
        }
        Err(Status::unknown("the stream ended without a result"))
    }

    /// [`Client::complete`] on a scene in memory.
    pub async fn complete_scene(
        &mut self,
        scene: &SceneInput,
        options_json: &str,
        timeout: Option<Duration>,
    ) -> Result<Completion, Status> {
        self.complete(
            crate::request::request_from_scene(scene, options_json),
            timeout,
        )
        .await
    }

    pub async fn grasp(
        &mut self,
        req: crate::proto::GraspRequest,
    ) -> Result<crate::proto::GraspResponse, Status> {
        let r = self.request(req, None)?;
        Ok(self.inner.grasp(r).await?.into_inner())
    }

    pub async fn place(
        &mut self,
        req: crate::proto::PlaceRequest,
    ) -> Result<crate::proto::PlaceResponse, Status> {
        let r = self.request(req, None)?;
        Ok(self.inner.place(r).await?.into_inner())
    }
}
