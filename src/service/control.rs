//! `Control`: list sensors, read and change scenes, read noise models and status.

use super::session::Session;
use super::{Shared, grpc, status};
use crate::scene::Scene;
use crate::wire::{check_sensor_id, noise_to_proto, proto};
use std::sync::Arc;
use std::sync::atomic::Ordering;
use tonic::{Request, Response, Status};

/// The Control service.
pub struct ControlService {
    shared: Arc<Shared>,
}

impl ControlService {
    pub(crate) fn new(shared: Arc<Shared>) -> Self {
        ControlService { shared }
    }

    fn session(&self, sensor: &str) -> Result<Arc<Session>, Status> {
        check_sensor_id(sensor).map_err(status::invalid_field)?;
        self.shared.sessions.get(sensor).ok_or_else(|| {
            Status::not_found(format!(
                "sensor_id: no sensor {sensor:?} has sent frames or been configured"
            ))
        })
    }
}

/// Status of one session on the wire.
pub fn status_of(s: &Session) -> proto::SensorStatus {
    let st = &s.stats;
    proto::SensorStatus {
        sensor_id: s.sensor.clone(),
        frames_received: st.frames_received.load(Ordering::Relaxed),
        frames_processed: st.frames_processed.load(Ordering::Relaxed),
        frames_rejected: st.frames_rejected.load(Ordering::Relaxed),
        reports: st.reports.load(Ordering::Relaxed),
        returns: st.returns.load(Ordering::Relaxed),
        last_sequence: st.last_sequence.load(Ordering::Relaxed),
        sequence_gaps: st.sequence_gaps.load(Ordering::Relaxed),
        noise: s.noise().as_ref().map(noise_to_proto),
        fault: s.fault().unwrap_or_default(),
    }
}

#[tonic::async_trait]
impl grpc::control_server::Control for ControlService {
    async fn list_sensors(
        &self,
        _request: Request<proto::ListSensorsRequest>,
    ) -> Result<Response<proto::ListSensorsResponse>, Status> {
        let sensors = self
            .shared
            .sessions
            .all()
            .iter()
            .map(|s| status_of(s))
            .collect();
        Ok(Response::new(proto::ListSensorsResponse { sensors }))
    }

    /// An empty sensor id reads the scene new sensors start with.
    async fn get_scene(
        &self,
        request: Request<proto::SensorRequest>,
    ) -> Result<Response<proto::SceneDocument>, Status> {
        let sensor_id = request.into_inner().sensor_id;
        let scene = if sensor_id.is_empty() {
            self.shared.sessions.default_scene()
        } else {
            self.session(&sensor_id)?.scene().as_ref().clone()
        };
        Ok(Response::new(proto::SceneDocument {
            sensor_id,
            toml: scene.to_toml(),
        }))
    }

    /// Validates, then applies between two frames (queued behind frames already
    /// accepted). An unknown sensor is configured ahead of its first frame; an
    /// empty sensor id changes the scene new sensors start with.
    async fn set_scene(
        &self,
        request: Request<proto::SetSceneRequest>,
    ) -> Result<Response<proto::SceneDocument>, Status> {
        let req = request.into_inner();
        check_sensor_id(&req.sensor_id).map_err(status::invalid_field)?;
        if let Some(c) = &self.shared.cluster {
            // A scene set here would reach one node's edge and no owner.
            return Err(Status::failed_precondition(format!(
                "this server is a node of the cluster at {}: every sensor runs the scene the nodes were                  started with (--scene); change it there, on every node",
                c.url()
            )));
        }
        let origin = if req.sensor_id.is_empty() {
            "SetScene(default)".to_string()
        } else {
            format!("SetScene({})", req.sensor_id)
        };
        let scene = Scene::from_toml_str(&req.toml, &origin).map_err(status::scene)?;
        if req.sensor_id.is_empty() {
            // Building once proves the scene makes a pipeline before it is stored.
            super::session::build_pipeline(&scene, "default").map_err(status::pipeline_build)?;
            self.shared.sessions.set_default_scene(scene.clone())?;
        } else {
            let session = self
                .shared
                .sessions
                .get_or_start(&req.sensor_id)
                .map_err(status::start)?;
            session
                .set_scene(scene.clone())
                .await
                .map_err(status::pipeline_build)?;
            self.shared.sessions.persist_scene(&req.sensor_id, &scene)?;
        }
        tracing::info!(sensor = %req.sensor_id, scene = %scene.name, "scene set");
        Ok(Response::new(proto::SceneDocument {
            sensor_id: req.sensor_id,
            toml: scene.to_toml(),
        }))
    }

    async fn get_noise_model(
        &self,
        request: Request<proto::SensorRequest>,
    ) -> Result<Response<proto::NoiseModel>, Status> {
        let sensor_id = request.into_inner().sensor_id;
        let noise = self.session(&sensor_id)?.noise().ok_or_else(|| {
            Status::failed_precondition(format!(
                "sensor {sensor_id:?} has no noise model yet (no frame processed)"
            ))
        })?;
        Ok(Response::new(noise_to_proto(&noise)))
    }

    async fn get_status(
        &self,
        request: Request<proto::SensorRequest>,
    ) -> Result<Response<proto::SensorStatus>, Status> {
        let sensor_id = request.into_inner().sensor_id;
        let session = self.session(&sensor_id)?;
        Ok(Response::new(status_of(&session)))
    }
}
