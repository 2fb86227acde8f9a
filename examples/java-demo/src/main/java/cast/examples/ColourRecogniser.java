package cast.examples;

import java.util.Map;

/**
 * The demo's colour recogniser in Java (configs/demo/colour-java.yaml), as
 * {@code cast_examples.vision:ColourRecogniser} in Python: names the colour of each region.
 */
public class ColourRecogniser extends Recogniser {
  /** The named colours and their mean RGB, as {@code cast_examples.scene.COLOURS}. */
  static final Map<String, double[]> COLOURS =
      Map.of(
          "red", new double[] {0.85, 0.12, 0.10},
          "green", new double[] {0.15, 0.70, 0.20},
          "blue", new double[] {0.12, 0.25, 0.85},
          "yellow", new double[] {0.90, 0.85, 0.15});

  /** Their order there, which breaks ties. */
  static final String[] ORDER = {"red", "green", "blue", "yellow"};

  public ColourRecogniser() {
    super("colour");
  }

  /** Nearest named colour to the region's mean RGB. */
  @Override
  protected String recognise(SceneObject.Builder region) {
    String colour = nameColour(region.getRed(), region.getGreen(), region.getBlue());
    region.setColour(colour);
    return colour;
  }

  /** The named colour nearest to a mean RGB ({@code cast_examples.scene.name_colour}). */
  static String nameColour(double red, double green, double blue) {
    String best = null;
    double bestDistance = Double.POSITIVE_INFINITY;
    for (String name : ORDER) {
      double[] c = COLOURS.get(name);
      double distance = square(red - c[0]) + square(green - c[1]) + square(blue - c[2]);
      if (distance < bestDistance) {
        best = name;
        bestDistance = distance;
      }
    }
    return best;
  }

  private static double square(double v) {
    return v * v;
  }
}
