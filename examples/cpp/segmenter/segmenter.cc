// The demo's segmenter in C++ (configs/demo.yaml, SEGMENTER_LANGUAGE=cpp): an
// unmanaged component that finds regions of interest in a synthetic scene and
// keeps them up to date. A port of cast_examples.vision:Segmenter and the
// parts of cast_examples/scene.py it uses; same arguments, same behaviour, so
// the rest of the demo (Python and Java recognisers, the answerer) cannot
// tell which one runs.
//
// args: objects (how many, up to 8), rate_hz (frames per second), seed,
//       move_every (frames between moves), remove_at (frame at which one
//       object is taken away; 0: never).
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <iostream>
#include <map>
#include <random>
#include <string>
#include <vector>

#include "cast/cast.h"
#include "castdemo/scene.pb.h"

namespace {

using cast::examples::SceneObject;

struct Rgb {
  double r, g, b;
};

// What the camera sees of each colour and shape (scene.py COLOURS, SHAPES).
const std::map<std::string, Rgb> kColours = {
    {"red", {0.85, 0.12, 0.10}},
    {"green", {0.15, 0.70, 0.20}},
    {"blue", {0.12, 0.25, 0.85}},
    {"yellow", {0.90, 0.85, 0.15}},
};
struct Outline {
  std::uint32_t corners;
  double fill;
};
const std::map<std::string, Outline> kShapes = {
    {"cube", {4, 0.95}},
    {"ball", {0, M_PI / 4}},
    {"cone", {3, 0.5}},
};

struct TrueObject {
  std::string label;
  std::string colour;
  std::string shape;
  double x;
  double y;
  double size;
};

// The table, left to right: the demo's questions are about these (scene.py _LAYOUT).
struct Placement {
  const char* colour;
  const char* shape;
  double x;
  double y;
};
const Placement kLayout[] = {
    {"green", "cone", -0.45, 0.30}, {"blue", "ball", -0.25, 0.55}, {"red", "cube", 0.00, 0.40},
    {"yellow", "cube", 0.20, 0.35}, {"red", "ball", 0.40, 0.60},   {"blue", "cube", 0.55, 0.25},
    {"green", "ball", -0.60, 0.65}, {"yellow", "cone", 0.70, 0.50},
};

double round_to_hundredths(double v) { return std::round(v * 100.0) / 100.0; }

class Segmenter : public cast::UnmanagedComponent {
 public:
  void configure(const cast::Args& args) override {
    const auto seed = static_cast<std::uint32_t>(args.getInt("seed", 7));
    rng_.seed(seed);
    const auto layoutSize = static_cast<std::int64_t>(std::size(kLayout));
    const std::int64_t count = std::clamp<std::int64_t>(args.getInt("objects", 6), 1, layoutSize);
    std::uniform_real_distribution<double> sizes(0.05, 0.09);
    for (std::int64_t i = 0; i < count; ++i) {
      const Placement& p = kLayout[i];
      scene_.push_back({"obj-" + std::to_string(i + 1), p.colour, p.shape, p.x, p.y,
                        std::round(sizes(rng_) * 1000.0) / 1000.0});
    }
    const double rate = args.getDouble("rate_hz", 4.0);
    if (rate <= 0) throw cast::InvalidArgumentError("argument 'rate_hz' must be positive");
    period_ = std::chrono::milliseconds(static_cast<std::int64_t>(1000.0 / rate));
    moveEvery_ = std::max<std::int64_t>(1, args.getInt("move_every", 6));
    removeAt_ = args.getInt("remove_at", 0);
  }

  // One frame per period: a new region, a removal, or a move.
  void run() override {
    std::uint32_t frame = 0;
    while (!waitForStop(period_)) {
      ++frame;
      auto unseen = std::find_if(scene_.begin(), scene_.end(), [&](const TrueObject& o) { return !ids_.count(o.label); });
      if (unseen != scene_.end()) {
        const std::string id = newId();
        add(id, region(*unseen, frame));
        ids_[unseen->label] = id;
        say("frame %u: new region %s at x=%+.2f", frame, unseen->label.c_str(), unseen->x);
      } else if (removeAt_ > 0 && frame == static_cast<std::uint64_t>(removeAt_) && ids_.size() > 1) {
        const std::string label = ids_.rbegin()->first;  // the last label in sorted order
        deleteEntry(ids_[label]);
        ids_.erase(label);
        scene_.erase(std::remove_if(scene_.begin(), scene_.end(), [&](const TrueObject& o) { return o.label == label; }),
                     scene_.end());
        say("frame %u: %s was taken off the table", frame, label.c_str());
      } else if (frame % moveEvery_ == 0 && !ids_.empty()) {
        std::uniform_int_distribution<std::size_t> pick(0, ids_.size() - 1);
        auto it = std::next(ids_.begin(), static_cast<std::ptrdiff_t>(pick(rng_)));
        move(it->first, frame);
      }
    }
  }

 private:
  // What the camera reports of an object: noisy colour, corners, fill.
  SceneObject region(const TrueObject& obj, std::uint32_t frame) {
    std::normal_distribution<double> noise(0.0, 0.05);
    auto jitter = [&](double v) { return std::clamp(v + noise(rng_), 0.0, 1.0); };
    const Rgb& rgb = kColours.at(obj.colour);
    const Outline& outline = kShapes.at(obj.shape);
    SceneObject r;
    r.set_label(obj.label);
    r.set_frame(frame);
    r.set_x(obj.x);
    r.set_y(obj.y);
    r.set_size(obj.size);
    r.set_red(jitter(rgb.r));
    r.set_green(jitter(rgb.g));
    r.set_blue(jitter(rgb.b));
    r.set_corners(outline.corners);
    r.set_fill(jitter(outline.fill));
    return r;
  }

  void move(const std::string& label, std::uint32_t frame) {
    auto obj = std::find_if(scene_.begin(), scene_.end(), [&](const TrueObject& o) { return o.label == label; });
    std::uniform_real_distribution<double> step(-0.1, 0.1);
    obj->y = round_to_hundredths(std::min(0.9, std::max(0.1, obj->y + step(rng_))));
    const std::string& id = ids_.at(label);
    // The recognisers write this entry too: lock, read, change, write.
    cast::LockGuard guard = lock(id, cast::LockMode::O, "", std::chrono::seconds(5));
    SceneObject r = get<SceneObject>(id);
    r.set_y(obj->y);
    r.set_frame(frame);
    overwrite(id, r);
    say("frame %u: %s moved to y=%.2f", frame, label.c_str(), obj->y);
  }

  template <class... A>
  void say(const char* format, A... args) {
    char line[256];
    std::snprintf(line, sizeof line, format, args...);
    std::cout << line << std::endl;
  }

  std::vector<TrueObject> scene_;
  std::map<std::string, std::string> ids_;  // label -> entry id, sorted by label
  std::mt19937 rng_;
  std::chrono::milliseconds period_{250};
  std::int64_t moveEvery_ = 6;
  std::int64_t removeAt_ = 0;
};

}  // namespace

CAST_COMPONENT_MAIN(Segmenter)
