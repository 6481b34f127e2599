// Traceable calibration records (issue 15): every calibration attempt, successful or not, kept
// in a database a line can query, audit and re-solve from.
//
// A record is the journal's content (session/journal.hpp) in its final form: the run's identity
// (run id, station, operator, lens id), the camera's identity, the posecal and ABI versions, the
// session config, the image size and locked settings, every keyframe as the journal's JSON
// record (exact doubles) with its image (PNG) when the session keeps images, and at the end the
// state, the result JSON (model, covariance, expected error, eps figures, verdict) and the
// finish time. Each call below is one transaction, so a crash loses at most the keyframe in
// flight; a run that never finished stays in state "running".
//
// Stores: SQLite (a file path), WAL mode, a busy timeout so that two stations writing one file
// wait for each other instead of failing; PostgreSQL (a `postgresql://` URL) so that the
// stations of a line share one server. One schema in both (records/sql.hpp holds what differs
// between them), version 1 (table posecal_schema; a newer version is refused, an older one
// migrated). A store that goes away during a run: records/record_writer.hpp.
#pragma once

#include <map>
#include <memory>
#include <opencv2/core.hpp>
#include <optional>
#include <string>
#include <vector>

#include "common/run_id.hpp"  // new_run_id
#include "select/engine.hpp"

namespace posecal {

struct RunIdentity {
  std::string run_id;  // a UUID (new_run_id)
  std::string station_id, operator_id, lens_id;
  std::string camera_uri, camera_id, camera_vendor, camera_model, camera_serial,
      camera_device_version;
  std::string posecal_version, abi_version;
  std::string config;   // the session config, JSON text
  std::string started;  // UTC, ISO 8601
};

struct RunSummary {
  RunIdentity identity;
  std::string state;     // running, converged, failed, interrupted, closed, killed
  std::string finished;  // "" while running
  std::string verdict;   // "", pass or fail
  std::optional<double> expected_error_px;
  int keyframes = 0;
  std::string note;  // killed: which process ended without finishing it, and when that was found
};

struct StoredKeyframe {
  int index = 0;
  std::string time;
  std::string record;  // the journal's keyframe JSON (keyframe_from_json reads it)
  std::vector<unsigned char> image_png;  // empty without images
};

struct RunRecord {
  RunSummary summary;
  int image_width = 0, image_height = 0;
  std::map<std::string, std::string> locked_settings;
  std::string result;  // the result JSON text, "" while running
  std::vector<StoredKeyframe> keyframes;
};

// A keyframe as a record stores it: the journal's record stamped now, its image as PNG (none if
// `image` is empty).
StoredKeyframe stored_keyframe(int index, const KeyframeRecord& record, const cv::Mat& image);

class RecordStore {
 public:
  // Opens (and creates) the store at `location`: a file path (SQLite) or a postgresql:// URL
  // (the database must exist; its tables are created). Throws Error(kIo) naming the store
  // (a URL without its password) and the cause if it cannot be opened or is not a posecal
  // record database, Error(kInvalidArgument) for a database of a newer schema version.
  static std::unique_ptr<RecordStore> open(const std::string& location);
  ~RecordStore();
  RecordStore(const RecordStore&) = delete;
  RecordStore& operator=(const RecordStore&) = delete;

  const std::string& location() const { return location_; }

  // Each is one transaction; each throws Error(kIo) naming the store and the cause
  // (e.g. "database or disk is full"). begin_run refuses a run id that exists
  // (Error(kInvalidArgument)): two runs never share a record. A run records its writer (host,
  // pid and the pid's start time); begin_run marks the runs of this host still "running"
  // whose writer is gone as "killed", with a note.
  void begin_run(const RunIdentity& run);
  void set_engine(const std::string& run_id, cv::Size image_size,
                  const std::map<std::string, std::string>& locked_settings);
  void add_keyframe(const std::string& run_id, const StoredKeyframe& keyframe);
  void finish_run(const std::string& run_id, const std::string& state,
                  const std::string& result_json, const std::string& verdict,
                  std::optional<double> expected_error_px);

  // Newest first.
  std::vector<RunSummary> list_runs() const;

  // The passed runs of one camera model and lens id, newest first, without their keyframes:
  // those with the verdict "pass", and those converged without a specification (no verdict).
  struct FleetRun {
    std::string run_id, serial, started, result;
  };
  std::vector<FleetRun> fleet_runs(const std::string& camera_model,
                                   const std::string& lens_id) const;
  // Error(kNotFound) naming the run id if there is none. A unique prefix of a run id is
  // accepted (as git accepts an abbreviated commit); an ambiguous one is Error(kInvalidArgument).
  RunRecord get_run(const std::string& run_id) const;

 private:
  struct Db;
  RecordStore(std::string location, std::unique_ptr<Db> db);
  std::string location_;
  std::unique_ptr<Db> db_;
};

}  // namespace posecal
